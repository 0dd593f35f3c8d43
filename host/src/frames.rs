//! Frame sources: where captured images come from. A camera's own software writes numbered
//! files into a directory ([`DirectorySource`] watches it); the virtual camera writes the same
//! files, so the rest of the host cannot tell them apart.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

/// A frame that appeared.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Arrived {
    /// The camera's frame number, parsed from the file name.
    pub frame: u64,
    /// The file.
    pub path: PathBuf,
    /// Size in bytes when it was seen complete.
    pub bytes: u64,
    /// When it was last written, if the file system says.
    pub modified: Option<std::time::SystemTime>,
}

/// A file-name template: literal text around one `{frame}` or `{frame:0N}` field.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pattern {
    prefix: String,
    suffix: String,
    width: usize,
}

impl Pattern {
    /// Parses `img_{frame:06}.png`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let err = || {
            format!("frame pattern `{s}`: expected one `{{frame}}` or `{{frame:0N}}` field, e.g. `img_{{frame:06}}.png`")
        };
        let open = s.find('{').ok_or_else(err)?;
        let close = s[open..].find('}').map(|c| open + c).ok_or_else(err)?;
        let field = &s[open + 1..close];
        let width = match field.strip_prefix("frame") {
            Some("") => 0,
            Some(w) => w
                .strip_prefix(":0")
                .and_then(|w| w.parse().ok())
                .filter(|&w: &usize| w <= 20)
                .ok_or_else(err)?,
            None => return Err(err()),
        };
        let suffix = &s[close + 1..];
        if suffix.contains(['{', '}']) || s[..open].contains('}') {
            return Err(err());
        }
        Ok(Self { prefix: s[..open].into(), suffix: suffix.into(), width })
    }

    /// The frame number in `name`, if it matches.
    pub fn frame_of(&self, name: &str) -> Option<u64> {
        let digits = name.strip_prefix(&self.prefix)?.strip_suffix(&self.suffix)?;
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) || digits.len() < self.width {
            return None;
        }
        digits.parse().ok()
    }

    /// The file name of frame `n`.
    pub fn name_of(&self, n: u64) -> String {
        format!("{}{:0width$}{}", self.prefix, n, self.suffix, width = self.width)
    }
}

type Listed = (PathBuf, u64, u64, Option<std::time::SystemTime>);

/// Watches a directory for new frame files. A file counts once its size has stayed the same
/// over two polls (cameras write in pieces), or at once if the camera software writes to a
/// temporary name and renames (the usual way).
#[derive(Debug)]
pub struct DirectorySource {
    dir: PathBuf,
    pattern: Pattern,
    seen: HashSet<PathBuf>,
    /// Candidates with the size seen at the previous poll.
    growing: Vec<(PathBuf, u64)>,
}

impl DirectorySource {
    /// Watches `dir` for files named by `pattern`; files already there are ignored.
    pub fn new(dir: &Path, pattern: Pattern) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        let mut s = Self { dir: dir.to_path_buf(), pattern, seen: HashSet::new(), growing: Vec::new() };
        for (path, ..) in s.list()? {
            s.seen.insert(path);
        }
        Ok(s)
    }

    /// The pattern's files: path, frame number, size, modification time.
    fn list(&self) -> std::io::Result<Vec<Listed>> {
        let mut out = Vec::new();
        for entry in std::fs::read_dir(&self.dir)? {
            let entry = entry?;
            let name = entry.file_name();
            let Some(frame) = name.to_str().and_then(|n| self.pattern.frame_of(n)) else { continue };
            let meta = entry.metadata()?;
            if meta.is_file() {
                out.push((entry.path(), frame, meta.len(), meta.modified().ok()));
            }
        }
        Ok(out)
    }

    /// The files of the pattern in the directory now that [`Self::poll`] has not reported yet
    /// (complete or still being written).
    pub fn unreported(&self) -> std::io::Result<HashSet<PathBuf>> {
        Ok(self.list()?.into_iter().map(|(p, ..)| p).filter(|p| !self.seen.contains(p)).collect())
    }

    /// Frames complete since the last poll, in frame order.
    pub fn poll(&mut self) -> std::io::Result<Vec<Arrived>> {
        let mut done = Vec::new();
        let mut growing = Vec::new();
        for (path, frame, bytes, modified) in self.list()? {
            if self.seen.contains(&path) {
                continue;
            }
            let stable = self.growing.iter().any(|(p, b)| *p == path && *b == bytes && bytes > 0);
            if stable {
                self.seen.insert(path.clone());
                done.push(Arrived { frame, path, bytes, modified });
            } else {
                growing.push((path, bytes));
            }
        }
        self.growing = growing;
        done.sort_by_key(|a| a.frame);
        Ok(done)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patterns_parse_match_and_name() {
        let p = Pattern::parse("img_{frame:06}.png").unwrap();
        assert_eq!(p.frame_of("img_000042.png"), Some(42));
        assert_eq!(p.frame_of("img_1234567.png"), Some(1_234_567));
        assert_eq!(p.frame_of("img_42.png"), None, "narrower than the zero-padded width");
        assert_eq!(p.frame_of("img_00004x.png"), None);
        assert_eq!(p.frame_of("img_000042.tif"), None);
        assert_eq!(p.name_of(7), "img_000007.png");
        let q = Pattern::parse("{frame}.exr").unwrap();
        assert_eq!(q.frame_of("12.exr"), Some(12));
        assert!(Pattern::parse("img.png").unwrap_err().contains("expected one `{frame}`"));
        assert!(Pattern::parse("{frame}_{frame}.png").is_err());
        assert!(Pattern::parse("{frame:6}.png").is_err());
    }

    #[test]
    fn a_directory_source_reports_each_complete_file_once() {
        let dir = std::env::temp_dir().join(format!("lightrig-frames-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("f_0001.raw"), b"old").unwrap();
        let mut src = DirectorySource::new(&dir, Pattern::parse("f_{frame:04}.raw").unwrap()).unwrap();
        std::fs::write(dir.join("f_0002.raw"), b"abc").unwrap();
        std::fs::write(dir.join("notes.txt"), b"x").unwrap();
        assert_eq!(src.poll().unwrap(), vec![], "seen once: might still be growing");
        std::fs::write(dir.join("f_0003.raw"), b"abcdef").unwrap();
        let got = src.poll().unwrap();
        assert_eq!(got.iter().map(|a| (a.frame, a.bytes)).collect::<Vec<_>>(), [(2, 3)]);
        let got = src.poll().unwrap();
        assert_eq!(got.iter().map(|a| (a.frame, a.bytes)).collect::<Vec<_>>(), [(3, 6)]);
        assert_eq!(src.poll().unwrap(), vec![]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
