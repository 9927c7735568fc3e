//! Bounded concurrency for inferences: slots, a short queue and a deadline. Held in
//! [`crate::jobs::Ctx`] so that every front end of one process shares it; the HTTP layer
//! applies it to POST /infer and POST /log_prob.

use std::sync::Arc;
use std::sync::atomic::AtomicUsize;
use std::time::Duration;

/// Bounds on `POST /infer`: at most `concurrency` inferences run at once, at most `queue`
/// more wait for a slot (503 + Retry-After beyond that), and each answers within
/// `deadline` (waiting included) or gets a 503.
#[derive(Clone, Copy, Debug)]
pub struct InferLimits {
    /// Most inferences running at once.
    pub concurrency: usize,
    /// Most requests waiting for a slot.
    pub queue: usize,
    /// Longest a request may take, waiting included.
    pub deadline: Duration,
}

impl Default for InferLimits {
    /// Two inferences per core, 32 per core waiting, 10 s each. A request costs ~10–30 ms
    /// of CPU, so a burst of a few dozen clients waits well under a second instead of
    /// being turned away; the deadline still bounds every wait.
    fn default() -> Self {
        let cores = std::thread::available_parallelism().map_or(2, usize::from);
        InferLimits { concurrency: 2 * cores, queue: 32 * cores, deadline: Duration::from_secs(10) }
    }
}

/// The running state of [`InferLimits`]: slots and the count of requests waiting for one.
pub struct InferGate {
    /// The bounds it enforces.
    pub limits: InferLimits,
    pub(crate) slots: Arc<tokio::sync::Semaphore>,
    pub(crate) waiting: AtomicUsize,
}

impl InferGate {
    /// A gate with all `limits.concurrency` slots free.
    pub fn new(limits: InferLimits) -> InferGate {
        InferGate {
            limits,
            slots: Arc::new(tokio::sync::Semaphore::new(limits.concurrency.max(1))),
            waiting: AtomicUsize::new(0),
        }
    }
}
