//! Step-time generation benchmark (filled in with `motion`).
fn main() {}
