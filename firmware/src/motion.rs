//! Trapezoidal stepper motion with exact integer step ticks (work in progress).
