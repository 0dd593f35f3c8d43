//! Calibration through the tank wall: to be written.
