//! Why a job failed, told twice: a public message for the client, stored in the job's
//! row and shown by GET /jobs/{id}, and the internal cause, which goes to the server log
//! with the job's id and nowhere else. The public message names what failed in the job's
//! own terms (the dataset, the model id, the field, the effect), never a file, a folder,
//! an object store's key or URL: those belong to the cause.

use crate::npe::NpeError;
use std::fmt;

/// A job's failure: what the client is told and, for the server's own failures, why.
///
/// `Display` writes the public message alone, and the cause is no `source()`: a
/// `JobError` formatted, or wrapped into another error and formatted with its chain,
/// never shows the cause. The cause is read to be logged ([`JobError::log`], and where a
/// caller logs it itself, [`JobError::cause`]).
#[derive(Debug)]
pub struct JobError {
    public: String,
    cause: Option<anyhow::Error>,
}

impl JobError {
    /// The client's error (bad params, an unknown model, data that does not fit):
    /// `message` is told as it is, so it must name no path.
    pub fn client(message: impl Into<String>) -> JobError {
        JobError { public: message.into(), cause: None }
    }

    /// The server's own failure (a file, the job store, the object store, a panic): the
    /// client is told `public`, the log gets `cause`.
    pub fn internal(public: impl Into<String>, cause: impl Into<anyhow::Error>) -> JobError {
        JobError { public: public.into(), cause: Some(cause.into()) }
    }

    /// What the client is told.
    pub fn public(&self) -> &str {
        &self.public
    }

    /// The server's own cause, if the failure is the server's.
    pub fn cause(&self) -> Option<&anyhow::Error> {
        self.cause.as_ref()
    }

    /// Whether the cause is an `E` (or holds one as its context): how a stop (`Stopped`)
    /// and a lost lease (`LeaseLost`) are told apart from failures.
    pub fn is<E: fmt::Display + fmt::Debug + Send + Sync + 'static>(&self) -> bool {
        self.cause.as_ref().is_some_and(|c| c.is::<E>())
    }

    /// Logs the failure of job `job`: the server's own with its cause (`error!`), the
    /// client's as a warning.
    pub fn log(&self, job: &str) {
        match &self.cause {
            Some(cause) => {
                tracing::error!(job = %job, error = %self.public, cause = %format!("{cause:#}"), "job failed")
            }
            None => tracing::warn!(job = %job, error = %self.public, "job failed"),
        }
    }

    /// An estimator's error: the client's input (an observation, settings, a prior, the
    /// data, told as `subject: why`) keeps its message, which names no file; the rest (a
    /// file, a checkpoint, an encoder) is the server's, told as `public`.
    pub fn npe(e: NpeError, subject: &str, public: impl Into<String>) -> JobError {
        use crate::dataset::DatasetError;
        match e {
            // Their message opens with the file or folder: only the reason is told.
            NpeError::Table { why, .. } | NpeError::Csv(DatasetError::Table { why, .. }) => {
                JobError::client(format!("{subject}: {why}"))
            }
            NpeError::Observation(_)
            | NpeError::Prior(_)
            | NpeError::Settings { .. }
            | NpeError::NoFiniteLoss { .. } => JobError::client(e.to_string()),
            e => JobError::internal(public, e),
        }
    }
}

impl fmt::Display for JobError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.public)
    }
}

impl std::error::Error for JobError {}

impl From<super::Stopped> for JobError {
    fn from(e: super::Stopped) -> JobError {
        JobError::internal(e.to_string(), e)
    }
}

impl From<super::LeaseLost> for JobError {
    fn from(e: super::LeaseLost) -> JobError {
        JobError::internal(e.to_string(), e)
    }
}

/// The job store (the database) is the server's: its errors are internal.
impl From<sqlx::Error> for JobError {
    fn from(e: sqlx::Error) -> JobError {
        JobError::internal("the job store could not be read or written", e)
    }
}

/// Short call sites: `.internal("the dataset's folder could not be created")?`.
pub trait JobContext<T> {
    /// The error as the server's own failure: the client is told `public`, the log the error.
    fn internal(self, public: impl Into<String>) -> Result<T, JobError>;
}

impl<T, E: Into<anyhow::Error>> JobContext<T> for Result<T, E> {
    fn internal(self, public: impl Into<String>) -> Result<T, JobError> {
        self.map_err(|e| JobError::internal(public, e))
    }
}

#[cfg(test)]
mod tests {
    use super::super::{LeaseLost, Stopped};
    use super::*;

    #[test]
    fn the_cause_is_logged_never_shown() {
        let io = std::io::Error::new(std::io::ErrorKind::PermissionDenied, "denied");
        let e = JobError::internal("the report could not be written", anyhow::Error::from(io).context("/srv/x/y"));
        assert_eq!(e.to_string(), "the report could not be written");
        assert_eq!(format!("{:#}", anyhow::Error::from(e)), "the report could not be written");
        let e = JobError::internal("the report could not be written", anyhow::anyhow!("/srv/x/y"));
        assert!(format!("{:#}", e.cause().unwrap()).contains("/srv/x/y"));
        assert_eq!(JobError::client("params.x has 1 values").public(), "params.x has 1 values");
    }

    #[test]
    fn stop_and_lease_loss_are_told_apart_through_the_cause() {
        let stopped = JobError::from(Stopped);
        assert!(stopped.is::<Stopped>() && !stopped.is::<LeaseLost>());
        assert!(JobError::from(LeaseLost).is::<LeaseLost>());
        assert!(!JobError::client("x").is::<Stopped>());
    }
}
