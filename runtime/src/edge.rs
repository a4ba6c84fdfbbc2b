//! Bounded edges between stage instances.
//!
//! An edge is a FIFO queue with a capacity and an overflow [`Policy`]. ractor mailboxes are
//! unbounded, so messages never travel in a mailbox: they wait in the edge's queue, and the
//! consumer's mailbox receives at most one "ready" notification per edge at a time (the
//! `scheduled` flag), so mailboxes stay bounded too.
//!
//! - `block`: the producer takes a permit from a semaphore of `capacity` permits before it
//!   enqueues, and the permit is released only when the consumer has *finished* handling the
//!   message. So messages queued plus messages being handled never exceed the capacity, and a
//!   fast producer waits for a slow consumer (backpressure).
//! - `latest`: the producer never waits; when the queue holds `capacity` messages the oldest
//!   one is dropped and counted. Newer lighting and frames supersede older ones.
//! - An edge may also be bounded in bytes (the encoded size of its messages): under `block`
//!   the producer also waits for that many bytes of room (a message larger than the bound
//!   takes all of it, so it travels alone); under `latest` the oldest messages are dropped
//!   until the new one fits. So capacity × message size cannot exhaust memory.
//!
//! This module knows nothing about actors: the consumer registers a wake-up callback.

use std::collections::VecDeque;
use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::control::RunControl;
use crate::message::AnyMessage;

/// What an edge does when it is full.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Policy {
    /// The producer waits until the consumer has room (backpressure).
    Block,
    /// The oldest queued message is dropped and counted.
    Latest,
}

impl fmt::Display for Policy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Policy::Block => "block",
            Policy::Latest => "latest",
        })
    }
}

impl std::str::FromStr for Policy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "block" => Ok(Policy::Block),
            "latest" => Ok(Policy::Latest),
            other => Err(format!(
                "unknown policy `{other}` (expected `block` or `latest`)"
            )),
        }
    }
}

/// Capacity and policy of one edge.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct EdgeSettings {
    /// Most messages queued (plus, for `block`, being handled) at once; at least 1.
    pub capacity: usize,
    /// What happens when the edge is full.
    pub policy: Policy,
}

/// The consumer of this edge has stopped or the run is aborting.
#[derive(Debug, Clone, thiserror::Error)]
#[error("edge {0} is closed (its consumer stopped)")]
pub struct EdgeClosed(pub String);

/// Under `block`: a message's slot, and its bytes of room when the edge is bounded in bytes.
type Permits = (OwnedSemaphorePermit, Option<OwnedSemaphorePermit>);

struct Queued {
    msg: AnyMessage,
    permit: Option<Permits>,
    bytes: usize,
    enqueued: Instant,
}

type Waker = Box<dyn Fn() + Send + Sync>;
type ReleaseHook = Arc<dyn Fn() + Send + Sync>;

/// Why [`Edge::try_push`] refused a message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TryPushError {
    /// The edge is closed.
    #[error("edge is closed")]
    Closed,
    /// A `block` edge has no room.
    #[error("edge is full")]
    Full,
}

/// Counters of one edge, updated by producers and read by metrics.
#[derive(Debug, Default)]
pub struct EdgeCounters {
    /// Messages accepted onto the edge.
    pub messages: AtomicU64,
    /// Bytes accepted (encoded size of each message).
    pub bytes: AtomicU64,
    /// Messages dropped by the `latest` policy.
    pub dropped: AtomicU64,
    /// Largest queue length seen.
    pub max_depth: AtomicU64,
}

/// One bounded queue from a producer instance's output port to a consumer instance's input.
pub struct Edge {
    name: String,
    settings: EdgeSettings,
    queue: Mutex<VecDeque<Queued>>,
    space: Arc<Semaphore>,
    scheduled: AtomicBool,
    closed: AtomicBool,
    waker: OnceLock<Waker>,
    release: OnceLock<ReleaseHook>,
    control: Arc<RunControl>,
    counters: EdgeCounters,
    /// The byte bound: its size and, under `block`, a semaphore of that many permits.
    bytes: Option<ByteBound>,
}

struct ByteBound {
    max: u32,
    space: Arc<Semaphore>,
    /// Bytes queued now (for `latest`; changed only under the queue's lock).
    queued: AtomicU64,
}

impl fmt::Debug for Edge {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Edge")
            .field("name", &self.name)
            .field("settings", &self.settings)
            .field("depth", &self.depth())
            .finish()
    }
}

impl Edge {
    /// A new, empty edge. `name` is used in logs and metrics.
    pub fn new(name: String, settings: EdgeSettings, control: Arc<RunControl>) -> Arc<Self> {
        Edge::bounded(name, settings, None, control)
    }

    /// A new, empty edge that also holds at most `max_bytes` of encoded messages (queued
    /// plus, under `block`, being handled); at most `u32::MAX`.
    pub fn bounded(
        name: String,
        settings: EdgeSettings,
        max_bytes: Option<u64>,
        control: Arc<RunControl>,
    ) -> Arc<Self> {
        assert!(settings.capacity > 0, "validation rejects zero capacity");
        let bytes = max_bytes.map(|m| {
            let max = m.clamp(1, u64::from(u32::MAX)) as u32;
            ByteBound {
                max,
                space: Arc::new(Semaphore::new(max as usize)),
                queued: AtomicU64::new(0),
            }
        });
        Arc::new(Edge {
            name,
            settings,
            queue: Mutex::new(VecDeque::with_capacity(settings.capacity)),
            space: Arc::new(Semaphore::new(settings.capacity)),
            scheduled: AtomicBool::new(false),
            closed: AtomicBool::new(false),
            waker: OnceLock::new(),
            release: OnceLock::new(),
            control,
            counters: EdgeCounters::default(),
            bytes,
        })
    }

    /// The byte bound, if any.
    pub fn max_bytes(&self) -> Option<u64> {
        self.bytes.as_ref().map(|b| u64::from(b.max))
    }

    /// Byte permits a message of `bytes` takes: all of the bound at most.
    fn byte_permits(&self, bytes: usize) -> Option<(Arc<Semaphore>, u32)> {
        let b = self.bytes.as_ref()?;
        Some((b.space.clone(), (bytes.min(b.max as usize) as u32).max(1)))
    }

    /// Edge name, `producer.port -> consumer.port`.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Capacity and policy.
    pub fn settings(&self) -> EdgeSettings {
        self.settings
    }

    /// Messages queued now (not counting one being handled).
    pub fn depth(&self) -> usize {
        self.lock().len()
    }

    /// Counters for metrics.
    pub fn counters(&self) -> &EdgeCounters {
        &self.counters
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<Queued>> {
        // A panic while holding this lock cannot leave the deque inconsistent.
        crate::toolkit::lock(&self.queue)
    }

    /// Registers the consumer's wake-up; called once, before any producer runs.
    pub fn set_waker(&self, waker: impl Fn() + Send + Sync + 'static) {
        if self.waker.set(Box::new(waker)).is_err() {
            panic!("edge {} has two consumers", self.name);
        }
        if self.depth() > 0 {
            self.wake();
        }
    }

    /// Registers a hook called each time a message leaves the edge for good: its consumer
    /// finished it, or `latest` dropped it. Cut edges return credit with it.
    pub fn set_release_hook(&self, hook: impl Fn() + Send + Sync + 'static) {
        if self.release.set(Arc::new(hook)).is_err() {
            panic!("edge {} has two release hooks", self.name);
        }
    }

    /// Closes the edge: blocked and future producers get [`EdgeClosed`].
    pub fn close(&self) {
        self.closed.store(true, Ordering::SeqCst);
        self.space.close();
    }

    /// Whether [`Edge::close`] was called.
    pub fn is_closed(&self) -> bool {
        self.closed.load(Ordering::SeqCst)
    }

    /// Enqueues `msg` (of encoded size `bytes`), waiting for room under `block`.
    pub async fn push(&self, msg: AnyMessage, bytes: usize) -> Result<(), EdgeClosed> {
        let closed = || EdgeClosed(self.name.clone());
        if self.is_closed() {
            return Err(closed());
        }
        let permit = match self.settings.policy {
            Policy::Block => {
                let slot = self
                    .space
                    .clone()
                    .acquire_owned()
                    .await
                    .map_err(|_| closed())?;
                let room = match self.byte_permits(bytes) {
                    Some((space, n)) => {
                        Some(space.acquire_many_owned(n).await.map_err(|_| closed())?)
                    }
                    None => None,
                };
                Some((slot, room))
            }
            Policy::Latest => None,
        };
        if self.is_closed() {
            return Err(closed());
        }
        self.enqueue(msg, bytes, permit);
        Ok(())
    }

    /// Enqueues `msg` without waiting: a full `block` edge refuses it.
    pub fn try_push(&self, msg: AnyMessage, bytes: usize) -> Result<(), TryPushError> {
        if self.is_closed() {
            return Err(TryPushError::Closed);
        }
        let refused = |e| match e {
            tokio::sync::TryAcquireError::Closed => TryPushError::Closed,
            tokio::sync::TryAcquireError::NoPermits => TryPushError::Full,
        };
        let permit = match self.settings.policy {
            Policy::Block => {
                let slot = self.space.clone().try_acquire_owned().map_err(refused)?;
                let room = match self.byte_permits(bytes) {
                    Some((space, n)) => Some(space.try_acquire_many_owned(n).map_err(refused)?),
                    None => None,
                };
                Some((slot, room))
            }
            Policy::Latest => None,
        };
        self.enqueue(msg, bytes, permit);
        Ok(())
    }

    fn enqueue(&self, msg: AnyMessage, bytes: usize, permit: Option<Permits>) {
        self.control.add_pending();
        let dropped = {
            let mut q = self.lock();
            let mut dropped = 0;
            if self.settings.policy == Policy::Latest {
                // Room for the new one: by count, then by bytes (never dropping the last).
                let over_bytes = || {
                    self.bytes.as_ref().is_some_and(|b| {
                        b.queued.load(Ordering::Relaxed) + bytes as u64 > u64::from(b.max)
                    })
                };
                while !q.is_empty() && (q.len() >= self.settings.capacity || over_bytes()) {
                    if let Some(old) = q.pop_front() {
                        self.unqueue_bytes(old.bytes);
                    }
                    dropped += 1;
                }
            }
            q.push_back(Queued {
                msg,
                permit,
                bytes,
                enqueued: Instant::now(),
            });
            if let Some(b) = &self.bytes {
                b.queued.fetch_add(bytes as u64, Ordering::Relaxed);
            }
            self.counters
                .max_depth
                .fetch_max(q.len() as u64, Ordering::Relaxed);
            dropped
        };
        for _ in 0..dropped {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
            self.control.done_pending();
            if let Some(hook) = self.release.get() {
                hook();
            }
        }
        self.counters.messages.fetch_add(1, Ordering::Relaxed);
        self.counters
            .bytes
            .fetch_add(bytes as u64, Ordering::Relaxed);
        self.wake();
    }

    fn wake(&self) {
        if !self.scheduled.swap(true, Ordering::SeqCst) {
            match self.waker.get() {
                Some(w) => w(),
                // No consumer yet: `set_waker` wakes it when it registers.
                None => self.scheduled.store(false, Ordering::SeqCst),
            }
        }
    }

    /// A message of `bytes` left the queue (call under the queue's lock).
    fn unqueue_bytes(&self, bytes: usize) {
        if let Some(b) = &self.bytes {
            b.queued.fetch_sub(bytes as u64, Ordering::Relaxed);
        }
    }

    /// Takes the oldest message. The consumer calls this once per wake-up, handles the
    /// message, drops the [`Delivery`], then calls [`Edge::rearm`].
    pub fn pop(self: &Arc<Self>) -> Option<Delivery> {
        let q = {
            let mut queue = self.lock();
            let q = queue.pop_front()?;
            self.unqueue_bytes(q.bytes);
            q
        };
        Some(Delivery {
            msg: q.msg,
            waited: q.enqueued.elapsed(),
            permit: q.permit,
            control: self.control.clone(),
            release: self.release.get().cloned(),
        })
    }

    /// After handling one message: wake the consumer again if more are queued.
    pub fn rearm(&self) {
        self.scheduled.store(false, Ordering::SeqCst);
        if self.depth() > 0 {
            self.wake();
        }
    }
}

/// A message taken from an edge. While it lives, the message counts as in the pipeline and,
/// under `block`, holds its permit: dropping it releases both.
pub struct Delivery {
    msg: AnyMessage,
    waited: Duration,
    permit: Option<Permits>,
    control: Arc<RunControl>,
    release: Option<ReleaseHook>,
}

impl Delivery {
    /// The type-erased message.
    pub fn message(&self) -> &AnyMessage {
        &self.msg
    }

    /// How long the message waited in the queue.
    pub fn waited(&self) -> Duration {
        self.waited
    }
}

impl Drop for Delivery {
    fn drop(&mut self) {
        // Free the room first: the release hook may grant a remote producer credit for it.
        drop(self.permit.take());
        self.control.done_pending();
        if let Some(hook) = &self.release {
            hook();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicUsize;

    fn edge(capacity: usize, policy: Policy) -> (Arc<Edge>, Arc<AtomicUsize>) {
        let e = Edge::new(
            "a.out -> b.in".into(),
            EdgeSettings { capacity, policy },
            Arc::default(),
        );
        let wakes = Arc::new(AtomicUsize::new(0));
        let w = wakes.clone();
        e.set_waker(move || {
            w.fetch_add(1, Ordering::SeqCst);
        });
        (e, wakes)
    }

    fn msg(i: u32) -> AnyMessage {
        Arc::new(i)
    }

    #[tokio::test]
    async fn latest_drops_oldest_and_counts() {
        let (e, wakes) = edge(3, Policy::Latest);
        for i in 0..10 {
            e.push(msg(i), 4).await.unwrap();
        }
        assert_eq!(e.depth(), 3);
        assert_eq!(e.counters().dropped.load(Ordering::SeqCst), 7);
        assert_eq!(e.counters().max_depth.load(Ordering::SeqCst), 3);
        assert_eq!(
            wakes.load(Ordering::SeqCst),
            1,
            "one wake-up while scheduled"
        );
        let got: Vec<u32> = std::iter::from_fn(|| e.pop())
            .map(|d| *d.message().downcast_ref::<u32>().unwrap())
            .collect();
        assert_eq!(got, vec![7, 8, 9]);
        assert_eq!(e.control.pending(), 0);
    }

    #[tokio::test]
    async fn block_waits_until_a_delivery_is_dropped() {
        let (e, _) = edge(2, Policy::Block);
        e.push(msg(0), 4).await.unwrap();
        e.push(msg(1), 4).await.unwrap();
        let third = tokio::time::timeout(Duration::from_millis(50), e.push(msg(2), 4)).await;
        assert!(
            third.is_err(),
            "a full block edge must make the producer wait"
        );
        let d = e.pop().unwrap();
        // Popped but still being handled: the permit is held.
        let fourth = tokio::time::timeout(Duration::from_millis(50), e.push(msg(3), 4)).await;
        assert!(fourth.is_err());
        drop(d);
        e.push(msg(4), 4).await.unwrap();
        assert_eq!(e.depth(), 2);
    }

    fn bounded(capacity: usize, policy: Policy, max_bytes: u64) -> Arc<Edge> {
        let e = Edge::bounded(
            "a.out -> b.in".into(),
            EdgeSettings { capacity, policy },
            Some(max_bytes),
            Arc::default(),
        );
        e.set_waker(|| {});
        e
    }

    #[tokio::test]
    async fn a_block_edge_bounded_in_bytes_waits_for_room_in_bytes() {
        // Room for a million messages, but only 1,000 bytes.
        let e = bounded(1_000_000, Policy::Block, 1_000);
        for i in 0..2 {
            e.push(msg(i), 400).await.unwrap();
        }
        let third = tokio::time::timeout(Duration::from_millis(50), e.push(msg(2), 400)).await;
        assert!(third.is_err(), "1,200 bytes on a 1,000-byte edge");
        assert_eq!(e.try_push(msg(3), 400), Err(TryPushError::Full));
        assert!(e.try_push(msg(3), 200).is_ok(), "200 more bytes fit");
        drop(e.pop().unwrap());
        e.push(msg(4), 400).await.unwrap();
        assert_eq!(e.depth(), 3);
        // A message larger than the bound travels alone: it waits for the whole bound.
        let e = bounded(8, Policy::Block, 1_000);
        e.push(msg(0), 10).await.unwrap();
        let e2 = e.clone();
        let big = tokio::spawn(async move { e2.push(msg(1), 5_000).await });
        tokio::time::sleep(Duration::from_millis(30)).await;
        assert!(!big.is_finished());
        drop(e.pop().unwrap());
        tokio::time::timeout(Duration::from_secs(5), big)
            .await
            .expect("the big one goes once the edge is empty")
            .unwrap()
            .unwrap();
    }

    #[tokio::test]
    async fn a_latest_edge_bounded_in_bytes_drops_the_oldest_until_the_new_one_fits() {
        let e = bounded(1_000_000, Policy::Latest, 1_000);
        for i in 0..10 {
            e.push(msg(i), 300).await.unwrap();
        }
        assert_eq!(e.depth(), 3, "three of 300 bytes fit in 1,000");
        assert_eq!(e.counters().dropped.load(Ordering::SeqCst), 7);
        e.push(msg(10), 5_000).await.unwrap();
        assert_eq!(e.depth(), 1, "a message over the bound replaces everything");
        let got = *e.pop().unwrap().message().downcast_ref::<u32>().unwrap();
        assert_eq!(got, 10);
        e.push(msg(11), 300).await.unwrap();
        assert_eq!(e.depth(), 1);
        assert_eq!(e.control.pending(), 1);
    }

    #[tokio::test]
    async fn close_wakes_a_blocked_producer() {
        let (e, _) = edge(1, Policy::Block);
        e.push(msg(0), 4).await.unwrap();
        let e2 = e.clone();
        let blocked = tokio::spawn(async move { e2.push(msg(1), 4).await });
        tokio::time::sleep(Duration::from_millis(20)).await;
        e.close();
        assert!(blocked.await.unwrap().is_err());
    }

    #[tokio::test]
    async fn rearm_wakes_again_only_when_messages_remain() {
        let (e, wakes) = edge(4, Policy::Block);
        e.push(msg(0), 4).await.unwrap();
        e.push(msg(1), 4).await.unwrap();
        assert_eq!(wakes.load(Ordering::SeqCst), 1);
        drop(e.pop());
        e.rearm();
        assert_eq!(wakes.load(Ordering::SeqCst), 2);
        drop(e.pop());
        e.rearm();
        assert_eq!(wakes.load(Ordering::SeqCst), 2);
        e.push(msg(2), 4).await.unwrap();
        assert_eq!(wakes.load(Ordering::SeqCst), 3);
    }
}
