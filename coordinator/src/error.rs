//! The coordinator's errors, named for what went wrong; the API maps them to HTTP statuses.

#[derive(Debug, thiserror::Error)]
pub enum CoordError {
    /// The request is malformed: bad JSON, a bad hash, a bundle path that cannot be laid out.
    #[error("{0}")]
    Invalid(String),
    /// No such job, chunk, file or bundle.
    #[error("{0}")]
    Unknown(String),
    /// The request contradicts what the coordinator holds: a stale lease, a chunk already
    /// merged, a finished or cancelled job, an idempotency key used for another spec.
    #[error("{0}")]
    Refused(String),
    /// The job cannot be rendered: its scene fails to load, or its settings exceed a limit.
    #[error("{0}")]
    Unrenderable(String),
    /// The request is larger than a limit allows.
    #[error("{0}")]
    TooLarge(String),
    /// The coordinator cannot take the request now (its in-flight budget is spent): try
    /// again shortly.
    #[error("{0}")]
    Busy(String),
    /// Storage failed (disk, database) or the like: worth trying again.
    #[error("internal error: {0}")]
    Internal(String),
}

impl CoordError {
    /// The same error, its message prefixed with `what` (which frame of a job it concerns).
    pub fn within(self, what: &str) -> CoordError {
        use CoordError::*;
        match self {
            Invalid(m) => Invalid(format!("{what}: {m}")),
            Unknown(m) => Unknown(format!("{what}: {m}")),
            Refused(m) => Refused(format!("{what}: {m}")),
            Unrenderable(m) => Unrenderable(format!("{what}: {m}")),
            TooLarge(m) => TooLarge(format!("{what}: {m}")),
            Busy(m) => Busy(format!("{what}: {m}")),
            Internal(m) => Internal(format!("{what}: {m}")),
        }
    }
}

impl From<std::io::Error> for CoordError {
    fn from(e: std::io::Error) -> Self {
        CoordError::Internal(e.to_string())
    }
}
impl From<rusqlite::Error> for CoordError {
    fn from(e: rusqlite::Error) -> Self {
        CoordError::Internal(format!("database: {e}"))
    }
}
