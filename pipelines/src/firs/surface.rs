//! Surface mode (`lightrig fit firs-surface`): to be written.
