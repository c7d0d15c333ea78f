//! The table of admitted connections and the choice of which to shed at the limit.

use std::collections::HashMap;
use std::future::Future;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::task::Context;

use tokio::sync::{Notify, oneshot};

use crate::budget::Held;
use tokio::time::Instant;

/// What the accept loop reads of a connection to choose which to shed.
#[derive(Debug)]
pub(super) struct Activity {
    /// Milliseconds from the table's epoch to the last byte read (or to the accept).
    pub(super) last_read_ms: AtomicU64,
    /// The first [`PREFACE_BYTES`](super::conn::PREFACE_BYTES) bytes have arrived.
    pub(super) preface: AtomicBool,
    /// Authenticated calls in flight ([`calls::Admit`](super::calls::Admit)).
    pub(super) in_flight: AtomicUsize,
    /// It has made an authenticated call ([`calls::Admit`](super::calls::Admit)).
    pub(super) authenticated: AtomicBool,
    /// Whose it is since that call, counted against that tenant's connections until it
    /// closes; `None` before, or on a server without tokens.
    pub(super) owner: Mutex<Option<Held>>,
    /// The peer's address, for the cap on strangers from one address.
    pub(super) peer: Option<IpAddr>,
}

impl Activity {
    /// What the choice reads, now.
    fn idle(&self) -> Idle {
        Idle {
            authenticated: self.authenticated.load(Ordering::Relaxed),
            preface: self.preface.load(Ordering::Relaxed),
            last_read_ms: self.last_read_ms.load(Ordering::Relaxed),
            in_flight: self.in_flight.load(Ordering::Acquire),
        }
    }
}

/// A connection's activity at one moment, for [`choose_to_shed`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Idle {
    /// It has made an authenticated call.
    authenticated: bool,
    /// It has sent the HTTP/2 preface.
    preface: bool,
    /// When it last sent a byte, in milliseconds from the table's epoch.
    last_read_ms: u64,
    /// Calls in flight.
    in_flight: usize,
}

/// The connection to close for a new one: among those with no authenticated call in flight,
/// those that never made an authenticated call first (a stranger's, whatever it holds: a health
/// Watch is no call in flight), among them those that never sent the preface, then the one idle
/// longest (the oldest on a tie). `None`: every connection has a call in flight.
fn choose_to_shed(conns: impl IntoIterator<Item = (u64, Idle)>) -> Option<u64> {
    conns
        .into_iter()
        .filter(|(_, idle)| idle.in_flight == 0)
        .min_by_key(|&(id, idle)| (idle.authenticated, idle.preface, idle.last_read_ms, id))
        .map(|(id, _)| id)
}

/// The connections admitted, which the accept loop sheds from. Shared by the loop and by every
/// connection, which removes itself when it closes. A std mutex: it is held for an insert, a
/// removal or one scan of the table, never across an await.
#[derive(Debug)]
pub(super) struct Table {
    /// What `last_read_ms` counts from.
    epoch: Instant,
    /// The connections.
    open: Mutex<Open>,
    /// Notified when a shed connection has closed.
    closed: Notify,
}

/// The table's contents.
#[derive(Debug, Default)]
struct Open {
    /// The next connection's key.
    next_id: u64,
    /// Admitted connections that are neither closed nor shed.
    conns: HashMap<u64, Entry>,
    /// Connections shed and not closed yet: their descriptors are still open.
    closing: usize,
}

impl Open {
    /// Closes connection `id` for another.
    fn shed(&mut self, id: u64) {
        if let Some(entry) = self.conns.remove(&id) {
            // The connection sees it at its next read (one is always pending) and closes.
            let _ = entry.close.send(());
            self.closing += 1;
        }
    }
}

/// Whether a connection was admitted by closing another, and why.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Shed {
    /// Nothing was closed.
    No,
    /// The server was at its connection limit.
    Limit,
    /// The new connection's address had its most connections that made no authenticated call.
    Peer,
}

/// One admitted connection in the table.
#[derive(Debug)]
struct Entry {
    /// What the choice reads.
    activity: Arc<Activity>,
    /// Sent or dropped to close the connection.
    close: oneshot::Sender<()>,
}

impl Table {
    pub(super) fn new() -> Table {
        Table {
            epoch: Instant::now(),
            open: Mutex::new(Open::default()),
            closed: Notify::new(),
        }
    }

    /// Connections shed and not closed yet.
    pub(super) fn closing(&self) -> usize {
        self.lock().closing
    }

    /// Returns once fewer than `most` shed connections are still closing.
    pub(super) async fn until_closing_below(&self, most: usize) {
        // `notify_one` keeps a permit when nobody waits: a close between the check and the wait
        // is not missed.
        while self.closing() >= most {
            self.closed.notified().await;
        }
    }

    fn lock(&self) -> MutexGuard<'_, Open> {
        self.open.lock().unwrap_or_else(PoisonError::into_inner)
    }

    pub(super) fn millis(&self, at: Instant) -> u64 {
        u64::try_from(at.saturating_duration_since(self.epoch).as_millis()).unwrap_or(u64::MAX)
    }

    /// Admits a connection from `peer`: when `per_peer` connections from that address have
    /// made no authenticated call, by shedding the longest idle of them ([`Shed::Peer`]); else
    /// below `max` at once, at `max` by shedding one ([`Shed::Limit`]). `None`: the table is
    /// full of connections with calls in flight.
    pub(super) fn admit(
        self: &Arc<Self>,
        max: usize,
        per_peer: usize,
        peer: Option<IpAddr>,
    ) -> Option<(Tracked, Shed)> {
        let now = Instant::now();
        let mut open = self.lock();
        let mut shed = Shed::No;
        if peer.is_some() {
            let strangers = open.conns.iter().filter(|(_, entry)| {
                entry.activity.peer == peer && !entry.activity.authenticated.load(Ordering::Acquire)
            });
            if strangers.clone().count() >= per_peer {
                let strangers = strangers.map(|(&id, entry)| (id, entry.activity.idle()));
                if let Some(victim) = choose_to_shed(strangers) {
                    open.shed(victim);
                    shed = Shed::Peer;
                }
            }
        }
        if open.conns.len() >= max {
            let victim = choose_to_shed(
                open.conns
                    .iter()
                    .map(|(&id, entry)| (id, entry.activity.idle())),
            )?;
            open.shed(victim);
            shed = Shed::Limit;
        }
        let id = open.next_id;
        open.next_id += 1;
        let activity = Arc::new(Activity {
            last_read_ms: AtomicU64::new(self.millis(now)),
            preface: AtomicBool::new(false),
            in_flight: AtomicUsize::new(0),
            authenticated: AtomicBool::new(false),
            owner: Mutex::new(None),
            peer,
        });
        let (close, closed) = oneshot::channel();
        open.conns.insert(
            id,
            Entry {
                activity: Arc::clone(&activity),
                close,
            },
        );
        let tracked = Tracked {
            table: Arc::clone(self),
            id,
            activity,
            closed,
            shed: false,
        };
        Some((tracked, shed))
    }
}

/// A connection's place in the [`Table`]; it leaves the table when dropped.
#[derive(Debug)]
pub(super) struct Tracked {
    /// The table.
    pub(super) table: Arc<Table>,
    /// Its key there.
    id: u64,
    /// What it shares with the table and its calls.
    pub(super) activity: Arc<Activity>,
    /// Ready when the accept loop sheds the connection.
    closed: oneshot::Receiver<()>,
    /// `closed` was ready (a oneshot may not be polled again).
    shed: bool,
}

impl Tracked {
    /// Whether the accept loop has shed this connection; registers the waker if not.
    pub(super) fn poll_shed(&mut self, cx: &mut Context<'_>) -> bool {
        if !self.shed && Pin::new(&mut self.closed).poll(cx).is_ready() {
            self.shed = true;
        }
        self.shed
    }
}

impl Drop for Tracked {
    fn drop(&mut self) {
        // Its tenant's connection given back.
        drop(
            self.activity
                .owner
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .take(),
        );
        let mut open = self.table.lock();
        if open.conns.remove(&self.id).is_none() {
            // It was shed, and is closed now.
            open.closing -= 1;
            drop(open);
            self.table.closed.notify_one();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::connections::in_flight::Call;
    use std::time::Duration;

    /// Longest a test waits for what should be immediate.
    const PATIENCE: Duration = Duration::from_secs(10);

    fn idle(preface: bool, last_read_ms: u64, in_flight: usize) -> Idle {
        Idle {
            authenticated: true,
            preface,
            last_read_ms,
            in_flight,
        }
    }

    #[test]
    fn the_longest_idle_without_a_call_is_shed_preface_less_first() {
        // Longest idle: the earliest last read.
        let conns = [
            (1, idle(true, 500, 0)),
            (2, idle(true, 100, 0)),
            (3, idle(true, 300, 0)),
        ];
        assert_eq!(choose_to_shed(conns), Some(2));
        // A call in flight (a unary call or an open stream) protects even the longest idle.
        let conns = [
            (1, idle(true, 500, 0)),
            (2, idle(true, 100, 1)),
            (3, idle(true, 300, 0)),
        ];
        assert_eq!(choose_to_shed(conns), Some(3));
        // A connection that never sent the preface goes first, however recent.
        let conns = [
            (1, idle(true, 100, 0)),
            (2, idle(false, 900, 0)),
            (3, idle(false, 950, 0)),
        ];
        assert_eq!(choose_to_shed(conns), Some(2));
        // Ties go to the oldest connection.
        let conns = [(7, idle(false, 5, 0)), (4, idle(false, 5, 0))];
        assert_eq!(choose_to_shed(conns), Some(4));
        // A connection that never made an authenticated call goes before any tenant's, however
        // recently it sent a byte.
        let stranger = Idle {
            authenticated: false,
            ..idle(true, 900, 0)
        };
        let conns = [(1, idle(false, 5, 0)), (2, stranger), (3, idle(true, 1, 0))];
        assert_eq!(choose_to_shed(conns), Some(2));
        // Every connection busy (or none at all): nothing to shed.
        let conns = [(1, idle(true, 1, 2)), (2, idle(false, 1, 1))];
        assert_eq!(choose_to_shed(conns), None);
        assert_eq!(choose_to_shed([]), None);
    }

    #[tokio::test]
    async fn admitting_at_the_limit_closes_the_chosen_connection() {
        let table = Arc::new(Table::new());
        let (mut first, shed) = table.admit(2, 2, None).unwrap();
        assert_eq!(shed, Shed::No);
        let (second, shed) = table.admit(2, 2, None).unwrap();
        assert_eq!(shed, Shed::No);
        // The first has sent its preface and has a call in flight; the second is silent.
        first.activity.preface.store(true, Ordering::Relaxed);
        let call = Call::new(&first.activity);
        let (third, shed) = table.admit(2, 2, None).unwrap();
        assert_eq!(shed, Shed::Limit);
        let mut second = second;
        let waker = std::task::Waker::noop();
        let mut cx = Context::from_waker(waker);
        assert!(second.poll_shed(&mut cx), "the silent one was not closed");
        assert!(!first.poll_shed(&mut cx));
        assert_eq!(table.lock().conns.len(), 2);
        assert_eq!(table.closing(), 1);
        // A shed connection, once closed, is no longer counted as closing; the accept loop,
        // waiting for that, goes on.
        drop(second);
        assert_eq!(table.lock().conns.len(), 2);
        assert_eq!(table.closing(), 0);
        tokio::time::timeout(PATIENCE, table.until_closing_below(1))
            .await
            .unwrap();
        // Both left have calls in flight: nothing to shed, the next one is over the limit.
        let third_call = Call::new(&third.activity);
        assert!(table.admit(2, 2, None).is_none());
        // A call ended: that connection may go now.
        drop(call);
        let (_fourth, shed) = table.admit(2, 2, None).unwrap();
        assert_eq!(shed, Shed::Limit);
        assert!(first.poll_shed(&mut cx));
        drop(third_call);
        drop(third);
        assert_eq!(table.lock().conns.len(), 1);
        drop(first);
        assert_eq!(table.closing(), 0);
    }

    #[tokio::test]
    async fn strangers_from_one_address_hold_at_most_their_cap() {
        let table = Arc::new(Table::new());
        let here = Some(IpAddr::from([10, 0, 0, 1]));
        let there = Some(IpAddr::from([10, 0, 0, 2]));
        let (tenants, shed) = table.admit(8, 2, here).unwrap();
        assert_eq!(shed, Shed::No);
        // A tenant's connection (it made an authenticated call) is no stranger.
        tenants
            .activity
            .authenticated
            .store(true, Ordering::Release);
        let (mut first, _) = table.admit(8, 2, here).unwrap();
        let (second, shed) = table.admit(8, 2, here).unwrap();
        assert_eq!(shed, Shed::No);
        // Another address has its own two.
        let (_elsewhere, shed) = table.admit(8, 2, there).unwrap();
        assert_eq!(shed, Shed::No);
        let (_third, shed) = table.admit(8, 2, here).unwrap();
        assert_eq!(shed, Shed::Peer);
        let waker = std::task::Waker::noop();
        let mut cx = Context::from_waker(waker);
        assert!(
            first.poll_shed(&mut cx),
            "the oldest stranger was not closed"
        );
        assert_eq!(table.lock().conns.len(), 4);
        drop((first, second, tenants));
    }
}
