//! The `lightrig` command line: argument parsing and each subcommand ([`cmd`]), and
//! `lightrig demo` ([`demo`]): a whole acquisition and fit on the virtual rig (`lightrig-sim`)
//! checked against its ground truth, one module per rig. The library of the same crate is
//! what the binary runs, so tests drive the commands in-process.

pub mod cmd;
pub mod demo;
pub mod error;
