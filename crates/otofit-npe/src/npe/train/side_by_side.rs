//! An ensemble's flows trained side by side, one thread each.
//!
//! A small table's flows train in seconds each, and their small batches split less well
//! over threads than flows do (SLCP on two cores: one flow 1.9× faster on two threads
//! than on one, two flows at once on a thread each 2.3× — docs/results/npe.md). So the
//! members of an ensemble train on lanes, one per member up to the threads, the threads
//! shared evenly between them; a lane takes the next member when its own ends. On a
//! one-thread lane (two cores, or five flows on up to nine), once it is the last lane
//! training, its member's epochs run on two threads. One and two threads train a member
//! to the same bits ([`super::parts`]), so there the model is that of one member after
//! another on one or two threads; with more threads per lane, that of one member after
//! another on as many threads as the lane has. The progress callback runs on the calling
//! thread, one report at a time, and stops every lane when it says so.

use super::{EpochReport, Finished, MemberRun, Result, Run, member_stream};
use rand_chacha::ChaCha8Rng;
use rayon::{ThreadPool, ThreadPoolBuilder};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;

/// The threads side-by-side members train on: a pool per lane, the threads shared
/// evenly, and, where a lane has one thread, a pool of two for its member left training
/// alone.
pub(super) struct Lanes {
    own: Vec<ThreadPool>,
    pair: Option<ThreadPool>,
}

impl Lanes {
    /// Lanes for `members` members still to train on this pool's threads: one per member
    /// up to the threads, each with its share of them (at least one). None (one after
    /// another) for fewer than two members or one thread, or when the threads cannot be
    /// started. A lane's thread count is fixed when training starts, so a member's weights
    /// depend on the thread count and the members only, never on which lane ends first.
    pub(super) fn for_members(members: usize) -> Option<Lanes> {
        let threads = rayon::current_num_threads();
        let lanes = threads.min(members);
        if lanes < 2 {
            return None;
        }
        let pool = |n: usize| ThreadPoolBuilder::new().num_threads(n).build().ok();
        let own = (0..lanes).map(|_| pool(threads / lanes)).collect::<Option<Vec<_>>>()?;
        let pair = if threads / lanes == 1 { Some(pool(2)?) } else { None };
        Some(Lanes { own, pair })
    }
}

/// One lane's threads for a member's epochs.
pub(super) struct Lane<'a> {
    own: &'a ThreadPool,
    pair: Option<&'a ThreadPool>,
    /// Lanes still training.
    training: &'a AtomicUsize,
}

impl Lane<'_> {
    /// Runs an epoch on the lane's threads; a one-thread lane's on two once no other lane
    /// is training (one and two threads give the same bits).
    pub(super) fn run<R: Send>(&self, epoch: impl FnOnce() -> R + Send) -> R {
        match self.pair {
            Some(pair) if self.own.current_num_threads() == 1 && self.training.load(Ordering::Acquire) <= 1 => {
                pair.install(epoch)
            }
            _ => self.own.install(epoch),
        }
    }
}

/// A report on its way to the calling thread, with where its answer goes.
type Report = (EpochReport, mpsc::SyncSender<bool>);

impl Run<'_> {
    /// Trains the ensemble's members from the first after `fin` on, side by side on
    /// `lanes`: the same members as [`Run::members`] trains one after another, each from
    /// its own seed and batch stream, added in order.
    pub(super) fn side_by_side(
        &self,
        rng: &ChaCha8Rng,
        mut fin: Finished,
        lanes: Lanes,
        progress: &mut dyn FnMut(&EpochReport) -> bool,
    ) -> Result<Finished> {
        let total = self.s.ensemble.max(1);
        let next = AtomicUsize::new(fin.records.len());
        let training = AtomicUsize::new(lanes.own.len());
        let stop = AtomicBool::new(false);
        let (tx, rx) = mpsc::channel::<Report>();
        let mut ended: Vec<MemberRun> = std::thread::scope(|scope| {
            let handles: Vec<_> = lanes
                .own
                .iter()
                .map(|own| {
                    let lane = Lane { own, pair: lanes.pair.as_ref(), training: &training };
                    let (tx, next, stop) = (tx.clone(), &next, &stop);
                    scope.spawn(move || {
                        let mut ended = vec![];
                        let mut report = |r: &EpochReport| {
                            let (answer, answered) = mpsc::sync_channel(1);
                            tx.send((r.clone(), answer)).is_ok() && answered.recv().unwrap_or(false)
                        };
                        while !stop.load(Ordering::Acquire) {
                            let member = next.fetch_add(1, Ordering::AcqRel);
                            if member >= total {
                                break;
                            }
                            let m = self.fresh(member, member_stream(rng, self.s.seed, member));
                            let (m, _) = self.member(m, Some(&lane), &mut report, &mut |_, _| {});
                            ended.push(m);
                        }
                        lane.training.fetch_sub(1, Ordering::AcqRel);
                        ended
                    })
                })
                .collect();
            drop(tx);
            // The reports, one at a time on this thread, every epoch trained; once one
            // says stop, every lane stops at its next epoch and starts no other member.
            let mut go = true;
            for (r, answer) in rx {
                go &= progress(&r);
                stop.store(!go, Ordering::Release);
                let _ = answer.send(go);
            }
            handles
                .into_iter()
                .flat_map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
                .collect()
        });
        ended.sort_by_key(|m| m.member);
        for m in ended {
            fin.add(m)?;
        }
        Ok(fin)
    }
}
