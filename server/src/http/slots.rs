//! The web endpoint's connection slots: at most [`MAX_CONNECTIONS`](super::MAX_CONNECTIONS)
//! sockets at once, of which one identity (a tenant's token, or the shared token) holds at most
//! [`PER_IDENTITY`]. A socket is a stranger's until its request names a token of the server:
//! when every slot is taken, a new socket closes the oldest stranger's (a silent socket, or a
//! request without a valid token), never an identified viewer's; with no stranger's to close it
//! is answered 503. A server without tokens has one viewer, everyone, whom only the total caps.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use tokio::sync::oneshot;

/// Most connections one identity may hold at once.
pub const PER_IDENTITY: usize = 8;

/// Who a request comes from, as the slots count it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Identity {
    /// No valid token (on a server that needs one): a stranger, closed first.
    Stranger,
    /// A server without tokens: everyone is the one viewer, capped only by the total.
    Everyone,
    /// A token's identity (its tenant's address; 0 for the shared token).
    Token(usize),
}

/// The endpoint's sockets.
#[derive(Debug)]
pub struct Slots {
    /// Most sockets at once.
    max: usize,
    /// What is open.
    open: Mutex<Open>,
}

/// The sockets open, and whose.
#[derive(Debug, Default)]
struct Open {
    /// The next socket's key (keys grow: the first is the oldest).
    next: u64,
    /// Sockets by key; a stranger's carries what closes it.
    conns: BTreeMap<u64, Option<oneshot::Sender<()>>>,
    /// Identified sockets by identity.
    by_identity: HashMap<usize, usize>,
}

/// One socket's slot: it leaves the table when dropped.
#[derive(Debug)]
pub struct Slot {
    /// The table.
    slots: Arc<Slots>,
    /// Its key there.
    key: u64,
    /// The identity it counts against, once identified.
    identity: Mutex<Option<usize>>,
}

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Slots {
    /// At most `max` sockets at once.
    pub fn new(max: usize) -> Arc<Slots> {
        Arc::new(Slots {
            max,
            open: Mutex::new(Open::default()),
        })
    }

    /// A slot for a new socket, closing the oldest stranger's at the limit, and what tells the
    /// socket it is closed; `None`: every slot is an identified viewer's.
    pub fn admit(self: &Arc<Self>) -> Option<(Slot, oneshot::Receiver<()>)> {
        let mut open = lock(&self.open);
        if open.conns.len() >= self.max {
            let oldest = open
                .conns
                .iter()
                .find_map(|(&key, close)| close.is_some().then_some(key))?;
            if let Some(Some(close)) = open.conns.remove(&oldest) {
                let _ = close.send(());
            }
        }
        let key = open.next;
        open.next += 1;
        let (close, closed) = oneshot::channel();
        open.conns.insert(key, Some(close));
        let slot = Slot {
            slots: Arc::clone(self),
            key,
            identity: Mutex::new(None),
        };
        Some((slot, closed))
    }
}

impl Slot {
    /// The socket's request comes from `identity`: a token's identity is no longer closed for
    /// a stranger, unless it holds [`PER_IDENTITY`] sockets already (`Err`: how many).
    pub fn identify(&self, identity: Identity) -> Result<(), usize> {
        let key = match identity {
            Identity::Stranger => return Ok(()),
            Identity::Everyone => None,
            Identity::Token(key) => Some(key),
        };
        let mut open = lock(&self.slots.open);
        if let Some(key) = key {
            let held = open.by_identity.get(&key).copied().unwrap_or(0);
            if held >= PER_IDENTITY {
                return Err(held);
            }
            *open.by_identity.entry(key).or_default() += 1;
            *lock(&self.identity) = Some(key);
        }
        if let Some(close) = open.conns.get_mut(&self.key) {
            *close = None;
        }
        Ok(())
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let mut open = lock(&self.slots.open);
        open.conns.remove(&self.key);
        if let Some(key) = *lock(&self.identity) {
            if let Some(n) = open.by_identity.get_mut(&key) {
                *n -= 1;
                if *n == 0 {
                    open.by_identity.remove(&key);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strangers_make_room_and_one_identity_holds_at_most_its_share() {
        let slots = Slots::new(4);
        let (stranger, mut stranger_closed) = slots.admit().unwrap();
        let mut tenant = Vec::new();
        for _ in 0..3 {
            let (slot, closed) = slots.admit().unwrap();
            slot.identify(Identity::Token(7)).unwrap();
            tenant.push((slot, closed));
        }
        // Full: the next socket closes the stranger's, not the tenant's.
        let (next, _next_closed) = slots.admit().unwrap();
        assert!(stranger_closed.try_recv().is_ok());
        drop(stranger);
        assert!(tenant.iter_mut().all(|(_, c)| c.try_recv().is_err()));
        // Full of identified viewers: nothing to close.
        next.identify(Identity::Everyone).unwrap();
        assert!(slots.admit().is_none());
        // One identity's cap.
        let many = Slots::new(2 * PER_IDENTITY);
        let held: Vec<_> = (0..PER_IDENTITY)
            .map(|_| {
                let (slot, _) = many.admit().unwrap();
                slot.identify(Identity::Token(1)).unwrap();
                slot
            })
            .collect();
        let (more, _) = many.admit().unwrap();
        assert_eq!(more.identify(Identity::Token(1)), Err(PER_IDENTITY));
        more.identify(Identity::Token(2)).unwrap();
        drop(held);
        drop(more);
        assert!(lock(&many.open).by_identity.is_empty());
        assert!(lock(&many.open).conns.is_empty());
    }
}
