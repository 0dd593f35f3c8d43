//! The `lightrig` subcommands, one module each: its arguments (`Args`) and what it does.

pub mod acquire;
pub mod calibrate;
pub mod device;
pub mod display;
pub mod fit;
pub mod flash;
pub mod flash_probe;
pub mod hdr;
pub(crate) mod live;
pub mod selfcheck;
pub mod sim;
pub mod soak;

use std::process::ExitCode;

use crate::error::CliError;

/// A command's result as the process's exit: the error printed, its code returned.
pub fn exit(result: Result<(), CliError>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", e.message);
            ExitCode::from(e.code)
        }
    }
}
