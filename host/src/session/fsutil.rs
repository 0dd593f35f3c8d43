//! Durable file operations on the session's own files only, and wall-clock time stamps.
//!
//! A session directory is input like any other: something may have been planted in it (a
//! symbolic link at a temporary's name, a folder swapped for a link while a run goes on). Every
//! file the session writes is therefore created new (`O_CREAT | O_EXCL`: a link at the name is
//! never followed) or, the journal, opened with `O_NOFOLLOW` and checked to be a regular file
//! with no other name; every folder it writes into is checked (not following links) to be a
//! real folder, and a leftover temporary is removed only when it is a regular file. Anything
//! else is refused ([`SessionError::Foreign`]), naming the path, what is there and what to do.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Component, Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use super::{io_at, Result, SessionError};

/// What to do about a temporary, a frame file's name or anything else the session itself
/// would have made: it never makes a link.
pub(super) const REMOVE: &str = "remove it and run again";

/// What to do about a link at one of the session's own files or folders (`manifest.json`,
/// `journal.jsonl`, a folder under `frames/`): it may lead to the session's own, moved.
pub(super) const OWN: &str = "if it leads to this session's own file or folder, move that here in place of \
     the link; otherwise remove the link; then run again";

/// What is at a path, a symbolic link there not followed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Entry {
    /// Nothing.
    Absent,
    /// A regular file.
    File,
    /// A folder.
    Dir,
    /// A symbolic link, and what it holds.
    Link(PathBuf),
    /// A FIFO, a socket, a device.
    Other,
}

/// What is at `path`, not following a link there (`lstat`).
pub(super) fn entry(path: &Path) -> Result<Entry> {
    match fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => Ok(Entry::Link(fs::read_link(path).unwrap_or_default())),
        Ok(m) if m.is_file() => Ok(Entry::File),
        Ok(m) if m.is_dir() => Ok(Entry::Dir),
        Ok(_) => Ok(Entry::Other),
        Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(Entry::Absent),
        Err(e) => Err(io_at(path)(e)),
    }
}

/// The refusal of `found` at `path`, where the session would write; `todo`: what to do.
pub(super) fn foreign(path: &Path, found: &Entry, todo: &str) -> SessionError {
    let what = match found {
        Entry::Link(to) => format!("a symbolic link (to {})", to.display()),
        Entry::File => "a file where the session's folder must be".to_string(),
        Entry::Dir => "a folder where the session's file must be".to_string(),
        Entry::Other => "not a regular file or folder (a FIFO, socket or device)".to_string(),
        Entry::Absent => "gone while the session was writing it".to_string(),
    };
    SessionError::Foreign {
        path: path.to_path_buf(),
        detail: format!(
            "{what}; a session writes only its own regular files and folders, never through a link: {todo}"
        ),
    }
}

/// An open of `path` that failed with `e`: refused when what is there is not a regular file
/// (a link `O_NOFOLLOW` or `O_EXCL` would not follow, a folder, a FIFO), else `e`.
fn refused_or_io(path: &Path, e: io::Error, todo: &str) -> SessionError {
    match entry(path) {
        Ok(found @ (Entry::Link(_) | Entry::Dir | Entry::Other)) => foreign(path, &found, todo),
        _ => io_at(path)(e),
    }
}

/// A symbolic link at the last component of the path is not followed: the open fails.
fn no_follow(o: &mut OpenOptions) -> &mut OpenOptions {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        o.custom_flags(libc::O_NOFOLLOW);
    }
    o
}

/// Creates `path`, a file that must not exist yet, for writing: `O_CREAT | O_EXCL` (and
/// `O_NOFOLLOW`), so that a link planted at the name is refused, never written through.
pub(super) fn create_new(path: &Path) -> Result<File> {
    no_follow(OpenOptions::new().write(true).create_new(true))
        .open(path)
        .map_err(|e| refused_or_io(path, e, REMOVE))
}

/// Opens `path` for reading, not through a symbolic link at its name.
pub(super) fn open_read(path: &Path) -> io::Result<File> {
    no_follow(OpenOptions::new().read(true)).open(path)
}

/// Opens the journal to read it and append to it, created if absent: not through a symbolic
/// link (`O_NOFOLLOW`), and only a regular file that has no other name (a hard link: appending
/// would change the file under that name too, outside the session).
pub(super) fn open_journal(path: &Path) -> Result<File> {
    let f = no_follow(OpenOptions::new().read(true).append(true).create(true))
        .open(path)
        .map_err(|e| refused_or_io(path, e, OWN))?;
    let m = f.metadata().map_err(io_at(path))?;
    if !m.is_file() {
        return Err(foreign(path, &Entry::Other, REMOVE));
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        if m.nlink() > 1 {
            return Err(SessionError::Foreign {
                path: path.to_path_buf(),
                detail: format!(
                    "a file with {} names (hard links): appending to it would change it under its other \
                     name(s) too, outside the session; give the session a journal of its own (copy it, \
                     then move the copy over {}) and run again",
                    m.nlink(),
                    path.display()
                ),
            });
        }
    }
    Ok(f)
}

/// Makes sure the folders `rel` (relative, each component a plain name) exist under `base`
/// as real folders: those missing are created, durably (their parent fsynced); a link, a file
/// or anything else on the way is refused. Checked on every call, not remembered: a folder may
/// be replaced by a link while the session is open.
pub(super) fn ensure_dirs(base: &Path, rel: &Path) -> Result<()> {
    let mut at = base.to_path_buf();
    for c in rel.components() {
        debug_assert!(matches!(c, Component::Normal(_)), "{}", rel.display());
        let parent = at.clone();
        at.push(c);
        match entry(&at)? {
            Entry::Dir => {}
            Entry::Absent => match fs::create_dir(&at) {
                Ok(()) => sync_dir(&parent).map_err(io_at(&parent))?,
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => match entry(&at)? {
                    Entry::Dir => {}
                    found => return Err(foreign(&at, &found, OWN)),
                },
                Err(e) => return Err(io_at(&at)(e)),
            },
            found => return Err(foreign(&at, &found, OWN)),
        }
    }
    Ok(())
}

/// Whether the folders `rel` all exist under `base` as real folders (`false` at the first one
/// missing); a link or anything else on the way is refused. Before removing under them.
pub(super) fn check_dirs(base: &Path, rel: &Path) -> Result<bool> {
    let mut at = base.to_path_buf();
    for c in rel.components() {
        at.push(c);
        match entry(&at)? {
            Entry::Dir => {}
            Entry::Absent => return Ok(false),
            found => return Err(foreign(&at, &found, OWN)),
        }
    }
    Ok(true)
}

/// Makes a directory's entries (files created, renamed or removed in it) durable.
pub fn sync_dir(dir: &Path) -> io::Result<()> {
    File::open(dir)?.sync_all()
}

/// Writes `bytes` to `path` atomically and durably: a temporary file beside it (`path` with
/// `.partial` appended) is created new, written and fsynced, renamed over `path`, and the
/// directory fsynced. After a crash `path` is either absent (or its old content) or complete.
///
/// `path` must be absent or a regular file (renamed over: its other names, if any, keep the
/// old content). A leftover temporary of a run that stopped is removed first when it is a
/// regular file; a link or anything else at either name is refused.
pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    match entry(path)? {
        Entry::Absent | Entry::File => {}
        found => return Err(foreign(path, &found, REMOVE)),
    }
    let tmp = partial_path(path);
    match entry(&tmp)? {
        Entry::Absent => {}
        Entry::File => fs::remove_file(&tmp).map_err(io_at(&tmp))?,
        found => return Err(foreign(&tmp, &found, REMOVE)),
    }
    let mut f = create_new(&tmp)?;
    f.write_all(bytes).map_err(io_at(&tmp))?;
    f.sync_all().map_err(io_at(&tmp))?;
    drop(f);
    fs::rename(&tmp, path).map_err(io_at(path))?;
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    sync_dir(dir).map_err(io_at(dir))
}

/// The temporary name [`write_atomic`] uses for `path`.
pub fn partial_path(path: &Path) -> std::path::PathBuf {
    let mut name = path.file_name().unwrap_or_default().to_os_string();
    name.push(super::PARTIAL_SUFFIX);
    path.with_file_name(name)
}

/// Now, as RFC 3339 in UTC with milliseconds: `2025-03-01T12:34:56.789Z`.
pub fn now_rfc3339() -> String {
    rfc3339(SystemTime::now())
}

/// `t` as RFC 3339 in UTC with milliseconds (times before 1970 print as 1970).
pub fn rfc3339(t: SystemTime) -> String {
    let d = t.duration_since(UNIX_EPOCH).unwrap_or_default();
    let secs = d.as_secs();
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    let (y, m, day) = civil_from_days(days);
    format!(
        "{y:04}-{m:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem / 60 % 60,
        rem % 60,
        d.subsec_millis()
    )
}

/// Proleptic Gregorian date of a day count from 1970-01-01 (H. Hinnant's algorithm).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn rfc3339_known_dates() {
        assert_eq!(rfc3339(UNIX_EPOCH), "1970-01-01T00:00:00.000Z");
        let t = UNIX_EPOCH + Duration::from_millis(951_782_400_123); // leap day 2000
        assert_eq!(rfc3339(t), "2000-02-29T00:00:00.123Z");
        let t = UNIX_EPOCH + Duration::from_secs(1_735_689_599); // last second of 2024
        assert_eq!(rfc3339(t), "2024-12-31T23:59:59.000Z");
    }
}
