//! Voice-coil synthesis (work in progress).
