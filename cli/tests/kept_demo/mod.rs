//! Where a demo test writes its output. With `LIGHTRIG_KEEP_DEMOS` set (CI sets it), a test's
//! demo goes to `$LIGHTRIG_KEEP_DEMOS/<name>` and stays there: the Python package's tests
//! (python/tests) read those sessions instead of acquiring them again. Otherwise it goes to the
//! system's temporary directory and is removed at the end.

use std::path::{Path, PathBuf};

/// The output directory of demo `name` (`temp` when nothing is kept), emptied.
pub fn out_dir(name: &str, temp: &str) -> PathBuf {
    let out = match std::env::var_os("LIGHTRIG_KEEP_DEMOS") {
        Some(keep) => Path::new(&keep).join(name),
        None => std::env::temp_dir().join(format!("{temp}-{}", std::process::id())),
    };
    let _ = std::fs::remove_dir_all(&out);
    out
}

/// The end of a test that passed: its output removed unless kept.
pub fn finish(out: &Path) {
    if std::env::var_os("LIGHTRIG_KEEP_DEMOS").is_none() {
        let _ = std::fs::remove_dir_all(out);
    }
}
