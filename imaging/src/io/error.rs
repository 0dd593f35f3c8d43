//! The error type of [`crate::io`].

use std::fmt;
use std::path::PathBuf;

/// What went wrong with which file. Display starts with the path, so a message from a batch job
/// points straight at the offending frame.
#[derive(Debug)]
#[non_exhaustive]
pub enum IoError {
    /// The file could not be opened, created or renamed.
    Open { path: PathBuf, source: std::io::Error },
    /// The file ends early (an interrupted copy or capture).
    Truncated { path: PathBuf, detail: String },
    /// A valid file using a feature this module does not handle.
    Unsupported { path: PathBuf, what: String },
    /// Bits per sample differ from what the caller (or the first file of a stack) expects.
    BitDepth { path: PathBuf, found: u8, expected: u8 },
    /// Width, height or channel count differ from the first file of a stack (or another layer).
    SizeMismatch { path: PathBuf, expected: (u32, u32, u8), found: (u32, u32, u8) },
    /// The file is corrupt in some other way.
    Decode { path: PathBuf, detail: String },
    /// Writing failed.
    Encode { path: PathBuf, detail: String },
    /// The image's [`Encoding`](super::Encoding) does not fit the output and the caller did not ask
    /// for a conversion.
    Encoding { path: PathBuf, detail: String },
    /// The in-memory image is inconsistent (sample count, channel count, names).
    InvalidImage { path: PathBuf, detail: String },
}

impl IoError {
    /// The file the error is about.
    pub fn path(&self) -> &std::path::Path {
        match self {
            IoError::Open { path, .. }
            | IoError::Truncated { path, .. }
            | IoError::Unsupported { path, .. }
            | IoError::BitDepth { path, .. }
            | IoError::SizeMismatch { path, .. }
            | IoError::Decode { path, .. }
            | IoError::Encode { path, .. }
            | IoError::Encoding { path, .. }
            | IoError::InvalidImage { path, .. } => path,
        }
    }
}

impl fmt::Display for IoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: ", self.path().display())?;
        match self {
            IoError::Open { source, .. } => write!(f, "{source}"),
            IoError::Truncated { detail, .. } => {
                write!(f, "truncated ({detail}); re-copy or re-capture the file")
            }
            IoError::Unsupported { what, .. } => write!(f, "unsupported: {what}"),
            IoError::BitDepth { found, expected, .. } => {
                write!(f, "wrong bit depth: {found}-bit samples, expected {expected}-bit")
            }
            IoError::SizeMismatch { expected: (ew, eh, ec), found: (w, h, c), .. } => write!(
                f,
                "size mismatch: {w}x{h} with {c} channel(s), expected {ew}x{eh} with {ec} channel(s) \
                 like the first image"
            ),
            IoError::Decode { detail, .. } => write!(f, "cannot decode: {detail}"),
            IoError::Encode { detail, .. } => write!(f, "cannot write: {detail}"),
            IoError::Encoding { detail, .. } => write!(f, "{detail}"),
            IoError::InvalidImage { detail, .. } => write!(f, "invalid image: {detail}"),
        }
    }
}

impl std::error::Error for IoError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            IoError::Open { source, .. } => Some(source),
            _ => None,
        }
    }
}
