//! Volume mode (`lightrig fit firs-volume`): to be written.
