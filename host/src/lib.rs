//! The lightrig host toolkit. This first slice holds the protocol self-check; transports,
//! the device client, planners, the session journal and the pipelines follow their issues.

pub mod selfcheck;
