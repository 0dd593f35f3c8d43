//! The error the fits (`lls_fit`, `firs_fit`) return: one message that says what was wrong,
//! where (file, step, field) and what to do.

/// Why a fit stopped: what, where, what to do.
#[derive(Debug, Clone, PartialEq)]
pub struct FitError(pub String);

impl std::fmt::Display for FitError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for FitError {}

pub(crate) fn fail(m: impl Into<String>) -> FitError {
    FitError(m.into())
}
