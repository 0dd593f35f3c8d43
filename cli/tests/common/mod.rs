//! What several test binaries share.

use std::path::{Path, PathBuf};

/// A fresh scratch directory in the system's temporary directory, removed when dropped unless
/// the test is failing (then it stays for a look, and its path is in the failure's message
/// wherever the test prints a file of it).
pub struct Scratch(PathBuf);

impl Scratch {
    /// `lightrig-<prefix>-<name>-<process id>`, emptied if a killed run left it.
    pub fn new(prefix: &str, name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("lightrig-{prefix}-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Scratch(dir)
    }
}

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}
