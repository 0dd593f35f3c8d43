//! How a command fails: a message and the exit code that tells scripts what kind of failure
//! it was (0 done, 1 failure, 2 usage, 3 device unreachable or refusing, 4 rig file or session
//! problem, 5 session complete with frames missing, 130 stopped by Ctrl-C or
//! `lightrig stop`).

use lightrig_host::bringup::BringUpError;

/// An error for the command line: message and exit code.
#[derive(Debug)]
pub struct CliError {
    /// Exit code.
    pub code: u8,
    /// What to print.
    pub message: String,
}

/// A [`CliError`].
pub fn err(code: u8, message: impl Into<String>) -> CliError {
    CliError { code, message: message.into() }
}

/// Exit code: something failed at run time.
pub const FAILURE: u8 = 1;
/// Exit code: the command line is wrong.
pub const USAGE: u8 = 2;
/// Exit code: the device could not be reached, or refused.
pub const DEVICE: u8 = 3;
/// Exit code: the rig file or the session is wrong.
pub const INPUT: u8 = 4;
/// Exit code: the session is complete but frames are missing (`resume --retake-missing`).
pub const INCOMPLETE: u8 = 5;
/// Exit code: stopped by Ctrl-C (128 + SIGINT, as shells report it) or `lightrig stop`.
pub const INTERRUPTED: u8 = 130;

impl From<BringUpError> for CliError {
    fn from(e: BringUpError) -> Self {
        match e {
            BringUpError::Device(m) => err(DEVICE, m),
            BringUpError::RigFile(m) => err(INPUT, m),
            BringUpError::Client(e @ lightrig_host::client::ClientError::Interrupted { .. }) => {
                err(INTERRUPTED, e.to_string())
            }
            BringUpError::Client(e) => err(DEVICE, e.to_string()),
        }
    }
}

/// A failure at run time (exit code 1) with `e`'s message.
pub fn failure(e: impl std::fmt::Display) -> CliError {
    err(FAILURE, e.to_string())
}

/// An I/O failure on `path` (exit code 1), naming the path.
pub fn io(path: &std::path::Path) -> impl Fn(std::io::Error) -> CliError + '_ {
    move |e| err(FAILURE, format!("{}: {e}", path.display()))
}
