//! Bounded concurrency for inferences: slots, a short queue and a deadline. Held in
//! [`crate::jobs::Ctx`] so that every front end of one process shares it; the HTTP layer
//! applies it to POST /infer and POST /log_prob.

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::AtomicUsize;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Longest a client may take to send an inference's body; 408 after. A real body is at
/// most a few hundred kilobytes and arrives in milliseconds.
pub const BODY_DEADLINE: Duration = Duration::from_secs(10);
/// Most inference bodies one client address may be sending at once; 429 beyond. Bodies
/// are read before a slot is taken, so a slow sender holds a task and its bytes, never a
/// slot; this bounds what one address can hold.
pub const UPLOADS_PER_ADDRESS: usize = 8;

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
    /// Bodies being received, per client address.
    uploads: Mutex<HashMap<IpAddr, usize>>,
}

/// A body being received from `addr`; counted until dropped.
pub struct Upload<'a> {
    gate: &'a InferGate,
    addr: IpAddr,
}

impl Drop for Upload<'_> {
    fn drop(&mut self) {
        let mut m = self.gate.uploads.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = m.get_mut(&self.addr) {
            *n -= 1;
            if *n == 0 {
                m.remove(&self.addr);
            }
        }
    }
}

impl InferGate {
    /// A gate with all `limits.concurrency` slots free.
    pub fn new(limits: InferLimits) -> InferGate {
        InferGate {
            limits,
            slots: Arc::new(tokio::sync::Semaphore::new(limits.concurrency.max(1))),
            waiting: AtomicUsize::new(0),
            uploads: Mutex::new(HashMap::new()),
        }
    }

    /// Counts a body being received from `addr`, or `None` when that address already
    /// sends [`UPLOADS_PER_ADDRESS`] of them.
    pub fn upload(&self, addr: IpAddr) -> Option<Upload<'_>> {
        let mut m = self.uploads.lock().unwrap_or_else(|e| e.into_inner());
        let n = m.entry(addr).or_insert(0);
        if *n >= UPLOADS_PER_ADDRESS {
            return None;
        }
        *n += 1;
        Some(Upload { gate: self, addr })
    }
}
