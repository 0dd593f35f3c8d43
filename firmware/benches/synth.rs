//! Voice-coil synthesis benchmark (filled in with `synth`).
fn main() {}
