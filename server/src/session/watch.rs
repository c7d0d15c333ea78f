//! What the web pages read of live sessions, kept so that reading never slows a Step: each
//! session's running summary ([`Tally`]: steps, episodes finished, recent scores) and the watch
//! slots of the environments someone is watching ([`Watch`]), plus the store's read-only views
//! over them ([`Store::summaries`], [`Store::watch`]).
//!
//! Step updates both while it holds the session's lock anyway: the tally with a few relaxed
//! atomic stores, the slots only while a viewer is attached (one atomic load otherwise); neither
//! allocates. A viewer copies a [`Frame`] (under a kilobyte) out under the slots' own short
//! lock and encodes it after letting go, so a slow or stalled viewer holds nothing a Step needs,
//! and a view never counts as using the session (it does not keep an idle session alive).

use std::sync::atomic::{AtomicI64, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError, Weak};

use super::envs::{Autoreset, Batch, Envs, ExpertActions};
use super::{Owner, Session, SessionError, SessionId, Store};
use crate::budget::Tenant;
use crate::sim::Restaurant;

/// Scores of the last episodes a session finished that its summary averages.
pub const RECENT_SCORES: usize = 16;
/// Last moves of a watched environment a [`Frame`] carries.
pub const RECENT_MOVES: usize = 12;

/// A session's running summary, updated by every Step.
#[derive(Debug, Default)]
pub struct Tally {
    /// Environment steps: a Step of N environments counts N.
    steps: AtomicU64,
    /// Episodes that ended (terminated or truncated) in a Step.
    episodes: AtomicU64,
    /// Final scores of the last [`RECENT_SCORES`] episodes, a ring indexed by `episodes`.
    scores: [AtomicI64; RECENT_SCORES],
}

/// A copy of a [`Tally`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TallyView {
    /// Environment steps so far.
    pub steps: u64,
    /// Episodes finished so far.
    pub episodes: u64,
    /// Mean final score of the last (up to [`RECENT_SCORES`]) episodes; `None` before the first.
    pub recent_mean: Option<f64>,
}

impl Tally {
    /// Counts a Step's environments and the episodes it ended.
    fn record(&self, batch: &Batch) {
        self.steps
            .fetch_add(u64::from(batch.num_envs), Ordering::Relaxed);
        // SAME_STEP reports the ended episode's score in `final_scores`, the others in `scores`.
        let scores = if batch.final_scores.is_empty() {
            &batch.scores
        } else {
            &batch.final_scores
        };
        let ended = batch.terminated.iter().zip(&batch.truncated);
        for (i, (&terminated, &truncated)) in ended.enumerate() {
            if terminated | truncated != 0 {
                let score = i32_at(scores, i);
                let n = self.episodes.fetch_add(1, Ordering::Relaxed);
                self.scores[(n % RECENT_SCORES as u64) as usize]
                    .store(i64::from(score), Ordering::Relaxed);
            }
        }
    }

    /// The counts now (a racing Step may be half counted: these are statistics).
    pub fn read(&self) -> TallyView {
        let episodes = self.episodes.load(Ordering::Relaxed);
        let n = episodes.min(RECENT_SCORES as u64) as usize;
        let recent_mean = (n > 0).then(|| {
            let sum: i64 = self.scores[..n]
                .iter()
                .map(|s| s.load(Ordering::Relaxed))
                .sum();
            sum as f64 / n as f64
        });
        TallyView {
            steps: self.steps.load(Ordering::Relaxed),
            episodes,
            recent_mean,
        }
    }
}

/// Environment `i`'s little-endian `i32` in a Batch array (or Step's actions); 0 if the array
/// has none (as the rewards of a Reset).
fn i32_at(array: &[u8], i: usize) -> i32 {
    array
        .get(4 * i..4 * i + 4)
        .map_or(0, |b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// One thing that happened to a watched environment.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Move {
    /// The environment's tick after it.
    pub tick: u32,
    /// The action taken (0 for a Reset, or a NEXT_STEP autoreset, which ignores it).
    pub action: u8,
    /// The reward it earned.
    pub reward: i32,
    /// The environment was reset by it (a Reset, or an autoreset).
    pub reset: bool,
}

/// What a viewer of one environment is shown: its state after the last Reset or Step, and
/// the moves that led there.
#[derive(Debug, Clone, Copy)]
pub struct Frame {
    /// Publications so far; a viewer skips a frame it has already sent.
    pub seq: u64,
    /// The game now; `None` until the environment is first reset.
    pub game: Option<Restaurant>,
    /// The session expert's choice in this state, when the session's Batches carry one.
    pub expert: Option<u8>,
    /// The last moves, a ring: the newest is at `(moves_len - 1) % RECENT_MOVES`.
    moves: [Move; RECENT_MOVES],
    /// Moves recorded so far.
    moves_len: u64,
}

impl Frame {
    fn new(game: Option<Restaurant>) -> Frame {
        Frame {
            seq: 1,
            game,
            expert: None,
            moves: [Move::default(); RECENT_MOVES],
            moves_len: 0,
        }
    }

    /// The last moves, newest first.
    pub fn moves(&self) -> impl Iterator<Item = Move> + '_ {
        let n = self.moves_len.min(RECENT_MOVES as u64) as usize;
        (0..n).map(move |k| {
            let i = (self.moves_len - 1 - k as u64) % RECENT_MOVES as u64;
            self.moves[i as usize]
        })
    }

    fn push(&mut self, m: Move) {
        self.moves[(self.moves_len % RECENT_MOVES as u64) as usize] = m;
        self.moves_len += 1;
    }
}

/// One watched environment: its latest frame, shared by all its viewers.
#[derive(Debug)]
struct Slot {
    /// Index of the environment in the session.
    env: usize,
    /// Viewers attached to it; the slot goes with the last.
    viewers: usize,
    /// The latest frame.
    frame: Frame,
}

/// The watched environments of a session.
#[derive(Debug, Default)]
pub struct Watch {
    /// Viewers attached to any environment: Step reads it without locking and skips the slots
    /// when it is 0. Changed only under the slots' lock (and, when attaching, the session's).
    viewers: AtomicUsize,
    /// One slot per watched environment. Locked by Step (under the session's lock) to publish,
    /// and by a viewer only to copy one frame out.
    slots: Mutex<Vec<Slot>>,
}

impl Watch {
    fn slots(&self) -> MutexGuard<'_, Vec<Slot>> {
        self.slots.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Publishes the environments' state after a Reset (`actions` empty) or a Step to the
    /// watched slots; nothing when nobody watches.
    fn publish(&self, envs: &Envs, actions: &[u8], batch: &Batch) {
        if self.viewers.load(Ordering::Relaxed) == 0 {
            return;
        }
        let stepped = !actions.is_empty();
        for slot in self.slots().iter_mut() {
            let i = slot.env;
            let frame = &mut slot.frame;
            frame.seq += 1;
            frame.game = envs.restaurant(i).copied();
            frame.expert = batch.expert_actions.get(i).copied();
            let reset = batch.reset.get(i).is_some_and(|&r| r != 0);
            // A partial Reset leaves unmasked environments as they were: nothing happened.
            if !stepped && !reset {
                continue;
            }
            frame.push(Move {
                tick: i32_at(&batch.ticks, i) as u32,
                action: if stepped { i32_at(actions, i) as u8 } else { 0 },
                reward: i32_at(&batch.rewards, i),
                reset,
            });
        }
    }
}

/// What the sessions page shows of one session.
#[derive(Debug, Clone)]
pub struct Summary {
    /// The session's ID.
    pub id: SessionId,
    /// Whose share it counts against.
    pub tenant: Arc<Tenant>,
    /// N.
    pub num_envs: usize,
    /// Which expert's choices its Batches carry.
    pub expert: ExpertActions,
    /// Its autoreset mode.
    pub autoreset: Autoreset,
    /// Its counts.
    pub tally: TallyView,
    /// Milliseconds since a request last used it.
    pub idle_ms: u64,
    /// Viewers watching it now.
    pub viewers: usize,
    /// Milliseconds since the store's epoch at its creation (orders the rows).
    pub created_ms: u64,
}

/// The sessions a viewer may see, and the server's totals.
#[derive(Debug, Default)]
pub struct Listing {
    /// At most the `max` asked for, oldest first.
    pub rows: Vec<Summary>,
    /// Sessions the viewer may see (more than `rows` when over `max`).
    pub visible: usize,
    /// Live sessions on the server.
    pub all_sessions: usize,
    /// Their environments.
    pub all_envs: u64,
}

/// A viewer attached to one environment of a session; detaches when dropped. It holds the
/// session weakly: a closed or expired session goes (and its memory with it) while watched.
#[derive(Debug)]
pub struct Viewer {
    /// The session.
    session: Weak<Session>,
    /// The watched environment.
    env: usize,
    /// N.
    num_envs: usize,
    /// Which expert's choices the session's Batches carry.
    expert: ExpertActions,
}

impl Viewer {
    /// Which expert's choices the session's Batches carry (and so [`Frame::expert`]).
    pub fn expert(&self) -> ExpertActions {
        self.expert
    }

    /// The watched environment.
    pub fn env(&self) -> usize {
        self.env
    }

    /// N.
    pub fn num_envs(&self) -> usize {
        self.num_envs
    }

    /// The latest frame; `None` once the session is gone.
    pub fn frame(&self) -> Option<Frame> {
        let session = self.session.upgrade()?;
        let slots = session.watch.slots();
        slots.iter().find(|s| s.env == self.env).map(|s| s.frame)
    }

    /// The session's counts; `None` once the session is gone.
    pub fn tally(&self) -> Option<TallyView> {
        Some(self.session.upgrade()?.tally.read())
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        let Some(session) = self.session.upgrade() else {
            return;
        };
        let watch = &session.watch;
        let mut slots = watch.slots();
        if let Some(k) = slots.iter().position(|s| s.env == self.env) {
            slots[k].viewers -= 1;
            if slots[k].viewers == 0 {
                slots.swap_remove(k);
            }
            watch.viewers.fetch_sub(1, Ordering::Relaxed);
        }
    }
}

impl Session {
    /// Counts a Step and shows it to the viewers (called with the environments locked).
    pub(super) fn stepped(&self, envs: &Envs, actions: &[u8], batch: &Batch) {
        self.tally.record(batch);
        self.watch.publish(envs, actions, batch);
    }

    /// Shows a Reset to the viewers (called with the environments locked).
    pub(super) fn was_reset(&self, envs: &Envs, batch: &Batch) {
        self.watch.publish(envs, &[], batch);
    }
}

impl Store {
    /// Whether `owner` has a session of this ID (not marking it used).
    pub fn exists(&self, owner: &Owner, id: &str) -> bool {
        self.lookup(owner, id).is_ok()
    }

    /// The summaries of `owner`'s live sessions, oldest first; at most `max` of them, the most
    /// recently used when there are more.
    pub fn summaries(&self, owner: &Owner, max: usize) -> Listing {
        let now = self.now_ms();
        let mut listing = Listing::default();
        for shard in &self.shared.shards {
            // The shard lock is held only to copy the pointers out: Steps look sessions up
            // through it.
            let sessions: Vec<(SessionId, Arc<Session>)> = shard
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .iter()
                .map(|(id, s)| (*id, Arc::clone(s)))
                .collect();
            for (id, s) in sessions {
                listing.all_sessions += 1;
                listing.all_envs += s.num_envs as u64;
                if !s.owner.is(owner) {
                    continue;
                }
                let tenant = s._charge.tenant();
                listing.rows.push(Summary {
                    id,
                    tenant: Arc::clone(tenant),
                    num_envs: s.num_envs,
                    expert: s.options.expert_actions,
                    autoreset: s.options.autoreset,
                    tally: s.tally.read(),
                    idle_ms: now.saturating_sub(s.last_used_ms.load(Ordering::Relaxed)),
                    viewers: s.watch.viewers.load(Ordering::Relaxed),
                    created_ms: s.created_ms,
                });
            }
        }
        let rows = &mut listing.rows;
        listing.visible = rows.len();
        if rows.len() > max {
            rows.sort_unstable_by_key(|r| r.idle_ms);
            rows.truncate(max);
        }
        rows.sort_unstable_by_key(|r| (r.created_ms, r.id.to_string()));
        listing
    }

    /// Attaches a viewer to environment `env` of session `id` of `owner`'s (another owner's
    /// session is not found, as an unknown one). The viewer's first frame is the environment as
    /// it is now, copied under the session's lock once: the lock a planner Step may hold for
    /// long, so callers on an async runtime call this on a blocking thread.
    pub fn watch(&self, owner: &Owner, id: &str, env: usize) -> Result<Viewer, SessionError> {
        let session = self.lookup(owner, id)?;
        let n = session.num_envs;
        if env >= n {
            return Err(SessionError::InvalidArgument(format!(
                "env must be in 0..={}, got {env}",
                n - 1
            )));
        }
        // The session's lock first, as Step takes them: no Step runs between the copy and the
        // slot's first publication.
        let envs = session.lock();
        let watch = &session.watch;
        let mut slots = watch.slots();
        match slots.iter_mut().find(|s| s.env == env) {
            Some(slot) => slot.viewers += 1,
            None => slots.push(Slot {
                env,
                viewers: 1,
                frame: Frame::new(envs.restaurant(env).copied()),
            }),
        }
        watch.viewers.fetch_add(1, Ordering::Relaxed);
        drop(slots);
        drop(envs);
        Ok(Viewer {
            session: Arc::downgrade(&session),
            env,
            num_envs: n,
            expert: session.options.expert_actions,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::{Caller, Limits, ResetArgs, SessionOptions};
    use crate::sim::Config;

    fn store() -> (Store, Caller, Caller) {
        let share = crate::budget::Share::default();
        let a = Caller::tenant(Arc::new(Tenant::new("tenant a".into(), share)));
        let b = Caller::tenant(Arc::new(Tenant::new("tenant b".into(), share)));
        (Store::new(Limits::default(), Arc::default()), a, b)
    }

    fn options(autoreset: Autoreset) -> SessionOptions {
        SessionOptions {
            autoreset,
            action_masks: false,
            expert_actions: ExpertActions::Reference,
        }
    }

    fn actions(n: usize, a: i32) -> Vec<u8> {
        (0..n).flat_map(|_| a.to_le_bytes()).collect()
    }

    #[test]
    fn summaries_count_steps_and_episodes_per_tenant() {
        let (store, a, b) = store();
        let config = Config {
            lives: 1,
            arrival_interval: 1,
            ..Config::default()
        };
        let (id, _) = store
            .create(&a, 2, config, options(Autoreset::NextStep), Some(1))
            .unwrap();
        store
            .create(&b, 1, config, options(Autoreset::SameStep), Some(2))
            .unwrap();
        let id = id.to_string();
        store.reset(&a.owner, &id, &ResetArgs::default()).unwrap();
        // Waiting only: the queue's patience runs out and the episodes end by losing a group.
        let mut steps = 0;
        while store.summaries(&a.owner, 10).rows[0].tally.episodes < 2 {
            store.step(&a.owner, &id, &actions(2, 0)).unwrap();
            steps += 2;
            assert!(steps < 100_000, "no episode ended");
        }
        let listing = store.summaries(&a.owner, 10);
        assert_eq!(
            (listing.visible, listing.all_sessions, listing.all_envs),
            (1, 2, 3)
        );
        let row = &listing.rows[0];
        assert_eq!(row.id.to_string(), id);
        assert_eq!(row.num_envs, 2);
        assert_eq!(row.tally.steps, steps);
        assert_eq!(row.tally.episodes, 2);
        assert!(row.tally.recent_mean.is_some());
        // SAME_STEP reports the ended episode's score in the final arrays: the tally takes it.
        let (same, _) = store
            .create(&b, 1, config, options(Autoreset::SameStep), Some(3))
            .unwrap();
        let same = same.to_string();
        let mut batch = store.reset(&b.owner, &same, &ResetArgs::default()).unwrap();
        // The expert earns points for 30 steps, then waiting loses the game.
        let mut played = 0;
        let final_score = loop {
            let choice = if played < 30 {
                batch.expert_actions[0]
            } else {
                0
            };
            batch = store
                .step(&b.owner, &same, &actions(1, i32::from(choice)))
                .unwrap();
            played += 1;
            if batch.terminated[0] == 1 {
                break i32::from_le_bytes(batch.final_scores[..4].try_into().unwrap());
            }
            assert!(played < 100_000, "the episode did not end");
        };
        assert!(final_score > 0, "the expert scored");
        let row = store
            .summaries(&b.owner, 10)
            .rows
            .into_iter()
            .find(|r| r.id.to_string() == same)
            .unwrap();
        assert_eq!(row.tally.episodes, 1);
        assert_eq!(row.tally.recent_mean, Some(f64::from(final_score)));
        let listing = store.summaries(&b.owner, 10);
        assert_eq!((listing.visible, listing.all_sessions), (2, 3));
        assert_eq!(store.summaries(&b.owner, 1).rows.len(), 1);
        assert_eq!(store.summaries(&Owner::Shared, 10).visible, 0);
    }

    #[test]
    fn a_viewer_sees_each_step_and_detaches() {
        let (store, a, b) = store();
        let (id, _) = store
            .create(&a, 3, Config::default(), options(Autoreset::NextStep), None)
            .unwrap();
        let id = id.to_string();
        assert!(matches!(
            store.watch(&b.owner, &id, 0),
            Err(SessionError::NotFound(_))
        ));
        assert!(matches!(
            store.watch(&a.owner, &id, 3),
            Err(SessionError::InvalidArgument(_))
        ));
        let viewer = store.watch(&a.owner, &id, 1).unwrap();
        assert!(viewer.frame().unwrap().game.is_none());
        let reset = store
            .reset(
                &a.owner,
                &id,
                &ResetArgs {
                    seed: Some(4),
                    ..ResetArgs::default()
                },
            )
            .unwrap();
        let frame = viewer.frame().unwrap();
        assert_eq!(frame.game.unwrap().tick(), 0);
        assert!(frame.moves().next().unwrap().reset);
        // Environment 1 plays the expert's choice, the others wait.
        let choice = reset.expert_actions[1];
        let mut acts = actions(3, 0);
        acts[4..8].copy_from_slice(&i32::from(choice).to_le_bytes());
        let batch = store.step(&a.owner, &id, &acts).unwrap();
        let frame = viewer.frame().unwrap();
        let last = frame.moves().next().unwrap();
        let reward = i32::from_le_bytes(batch.rewards[4..8].try_into().unwrap());
        assert_eq!((last.action, last.reward, last.tick), (choice, reward, 1));
        assert!(reward > 0, "the expert's first move earns points");
        assert_eq!(frame.moves().count(), 2);
        assert_eq!(frame.expert, Some(batch.expert_actions[1]));
        let obs = frame.game.unwrap().observation().map(|v| v as u8);
        assert_eq!(obs[..], batch.observations[40..80]);
        let second = store.watch(&a.owner, &id, 1).unwrap();
        assert_eq!(store.summaries(&a.owner, 10).rows[0].viewers, 2);
        drop(viewer);
        drop(second);
        assert_eq!(store.summaries(&a.owner, 10).rows[0].viewers, 0);
        // Watching is not using: the idle clock keeps running; a closed session ends the view.
        let viewer = store.watch(&a.owner, &id, 0).unwrap();
        store.close(&a.owner, &id).unwrap();
        assert!(viewer.frame().is_none());
        assert_eq!(store.live(), 0);
    }
}
