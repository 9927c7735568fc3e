//! An ensemble's flows trained side by side, one lane each, checkpointed or not.
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
//!
//! A checkpoint holds each member's own state, not one moment of the whole ensemble:
//! when one is due, the calling thread asks each lane for its member's state at that
//! member's next epoch and writes the checkpoint once every lane has answered (or has no
//! member left); one is written too when a member ends and at the end or a stop. The
//! lanes are set by the threads and the ensemble's size, not by the members left, so a
//! resumed training trains each member on the threads the uninterrupted one did.

use super::{Ended, EpochReport, Finished, MemberRun, Result, Run, Saver, Snapshot, Start, member_stream};
use crate::npe::NpeError;
use rand_chacha::ChaCha8Rng;
use rayon::{ThreadPool, ThreadPoolBuilder};
use std::cell::Cell;
use std::collections::{BTreeMap, VecDeque};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// The threads the members train on: a pool per lane, the threads shared evenly, and,
/// where two or more lanes have one thread each, a pool of two for a member left training
/// alone.
pub(super) struct Lanes {
    own: Vec<ThreadPool>,
    pair: Option<ThreadPool>,
}

impl Lanes {
    /// Lanes for an ensemble of `members` on this pool's threads: one per member up to
    /// the threads, each with its share of them (at least one); one lane with every
    /// thread for one member or one thread. A lane's thread count is fixed by the thread
    /// count and the ensemble's size, so a member's weights depend on those only, never
    /// on which lane ends first or on how many members a resumed training had left.
    pub(super) fn for_members(members: usize) -> Result<Lanes> {
        let threads = rayon::current_num_threads();
        let lanes = threads.min(members).max(1);
        let pool = |n: usize| {
            ThreadPoolBuilder::new().num_threads(n).build().map_err(|e| NpeError::Threads { why: e.to_string() })
        };
        let own = (0..lanes).map(|_| pool(threads / lanes)).collect::<Result<Vec<_>>>()?;
        let pair = if lanes > 1 && threads / lanes == 1 { Some(pool(2)?) } else { None };
        Ok(Lanes { own, pair })
    }

    /// One lane of `threads` threads: every member one after another on them.
    #[cfg(test)]
    pub(super) fn one(threads: usize) -> Lanes {
        Lanes { own: vec![ThreadPoolBuilder::new().num_threads(threads).build().unwrap()], pair: None }
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

/// What the calling thread tells a lane after a report.
#[derive(Clone, Copy)]
struct Answer {
    /// Go on training.
    go: bool,
    /// Send the member's state for a checkpoint.
    state: bool,
}

/// A lane's message to the calling thread; each names its lane.
enum Message {
    /// An epoch's report, and where its answer goes.
    Report(usize, EpochReport, mpsc::SyncSender<Answer>),
    /// A member's state for the checkpoint (none: it could not be encoded), and how long
    /// encoding it took.
    State(usize, Option<Snapshot>, Duration),
    /// The lane has no member left to train.
    Exit(usize),
}

/// A lane's part in a checkpoint round.
#[derive(Clone, Copy, PartialEq)]
enum Round {
    /// Not asked yet: it will be at its next report.
    Ask,
    /// Asked; its member's state is on its way.
    Asked,
    /// Answered, or training no more.
    Done,
}

impl Run<'_> {
    /// Trains the ensemble's members from `start` on, side by side on `lanes`, offering
    /// `saver` their states as they go ([module docs](self)). Each member trains from its
    /// own seed and batch stream, so the model is the same whichever lane trains which
    /// member; member 0 uses the seed and the batch stream `rng` exactly as a single model
    /// does, so a one-member ensemble is the single model. The members are added in order.
    pub(super) fn side_by_side(
        &self,
        rng: &ChaCha8Rng,
        start: Start,
        lanes: Lanes,
        mut saver: Option<&mut Saver>,
        progress: &mut dyn FnMut(&EpochReport) -> bool,
    ) -> Result<Finished> {
        let total = self.s.ensemble.max(1);
        let Start { mut fin, mut ended, under_way } = start;
        let checkpointing = saver.is_some();
        // The members' states as the checkpoint holds them, the resumed ones from the start.
        let mut states = BTreeMap::new();
        if checkpointing {
            let resumed = ended.iter().map(Snapshot::ended).chain(under_way.iter().map(Snapshot::of));
            states.extend(resumed.filter_map(Result::ok).map(|s| (s.member(), s)));
        }
        // The members to train, in order: those under way go on, the others start fresh.
        let mut todo: VecDeque<(usize, Option<MemberRun>)> = VecDeque::new();
        let mut under_way: BTreeMap<usize, MemberRun> = under_way.into_iter().map(|m| (m.member, m)).collect();
        for member in fin.records.len()..total {
            if !ended.iter().any(|e| e.member == member) {
                todo.push_back((member, under_way.remove(&member)));
            }
        }
        let todo = Mutex::new(todo);
        let training = AtomicUsize::new(lanes.own.len());
        let stop = AtomicBool::new(false);
        let (tx, rx) = mpsc::channel::<Message>();
        let trained: Vec<Ended> = std::thread::scope(|scope| {
            let handles: Vec<_> = lanes
                .own
                .iter()
                .enumerate()
                .map(|(i, own)| {
                    let lane = Lane { own, pair: lanes.pair.as_ref(), training: &training };
                    let (tx, todo, stop) = (tx.clone(), &todo, &stop);
                    scope.spawn(move || {
                        let mut trained = vec![];
                        let asked = Cell::new(false);
                        let mut report = |r: &EpochReport| {
                            let (answer, answered) = mpsc::sync_channel(1);
                            let sent = tx.send(Message::Report(i, r.clone(), answer)).is_ok();
                            let a = sent.then(|| answered.recv().ok()).flatten();
                            let a = a.unwrap_or(Answer { go: false, state: false });
                            asked.set(a.state);
                            a.go
                        };
                        let send = |encode: &dyn Fn() -> super::CheckpointResult<Snapshot>, member: usize| {
                            let t0 = Instant::now();
                            let snapshot =
                                encode().map_err(|why| tracing::warn!(member, %why, "member state not checkpointed"));
                            let _ = tx.send(Message::State(i, snapshot.ok(), t0.elapsed()));
                        };
                        while !stop.load(Ordering::Acquire) {
                            let next = todo.lock().unwrap_or_else(|p| p.into_inner()).pop_front();
                            let Some((member, resumed)) = next else { break };
                            let m =
                                resumed.unwrap_or_else(|| self.fresh(member, member_stream(rng, self.s.seed, member)));
                            let (m, end) = self.member(m, &lane, &mut report, &mut |m, force| {
                                if checkpointing && (asked.take() || force) {
                                    send(&|| Snapshot::of(m), m.member);
                                }
                            });
                            let m = m.ended();
                            if checkpointing && end.done {
                                send(&|| Snapshot::ended(&m), member);
                                asked.set(false);
                            }
                            trained.push(m);
                        }
                        lane.training.fetch_sub(1, Ordering::AcqRel);
                        let _ = tx.send(Message::Exit(i));
                        trained
                    })
                })
                .collect();
            drop(tx);
            // The reports, one at a time on this thread, every epoch trained; once one
            // says stop, every lane stops at its next epoch and starts no other member.
            let mut go = true;
            let mut round: Option<Vec<Round>> = None;
            let mut exited = vec![false; handles.len()];
            let mut unsaved = false;
            // The lanes' time encoding states since the last checkpoint: part of its cost.
            let mut encoding = Duration::ZERO;
            for message in rx {
                let mut write = false;
                match message {
                    Message::Report(lane, r, answer) => {
                        go &= progress(&r);
                        stop.store(!go, Ordering::Release);
                        if round.is_none() && saver.as_ref().is_some_and(|sv| sv.due()) {
                            round = Some(exited.iter().map(|&x| if x { Round::Done } else { Round::Ask }).collect());
                        }
                        let ask = match round.as_mut().map(|r| &mut r[lane]) {
                            Some(slot) if *slot == Round::Ask => {
                                *slot = Round::Asked;
                                true
                            }
                            _ => false,
                        };
                        let _ = answer.send(Answer { go, state: ask });
                    }
                    Message::State(lane, snapshot, took) => {
                        encoding += took;
                        if let Some(s) = snapshot {
                            // A member's end is saved at once.
                            write = s.done();
                            states.insert(s.member(), s);
                            unsaved = true;
                        }
                        if let Some(r) = round.as_mut().filter(|r| r[lane] == Round::Asked) {
                            r[lane] = Round::Done;
                        }
                    }
                    Message::Exit(lane) => {
                        exited[lane] = true;
                        if let Some(r) = round.as_mut() {
                            r[lane] = Round::Done;
                        }
                    }
                }
                if round.as_ref().is_some_and(|r| r.iter().all(|&a| a == Round::Done)) {
                    round = None;
                    write = true;
                }
                if let Some(sv) = saver.as_deref_mut().filter(|_| write && unsaved) {
                    sv.save(&fin, states.values(), std::mem::take(&mut encoding));
                    unsaved = false;
                }
            }
            // At the end, or a stop: the states the lanes sent last.
            if let Some(sv) = saver.filter(|_| unsaved) {
                sv.save(&fin, states.values(), encoding);
            }
            handles
                .into_iter()
                .flat_map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
                .collect()
        });
        ended.extend(trained);
        ended.sort_by_key(|m| m.member);
        for m in ended {
            fin.add(m)?;
        }
        Ok(fin)
    }
}
