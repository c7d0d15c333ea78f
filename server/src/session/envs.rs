//! The environments of one session and what Reset and Step do to them: seeds per environment,
//! explicit arrival lists, autoreset (Gymnasium 1.x `NEXT_STEP` and `SAME_STEP`), and the packed
//! little-endian arrays of a [`Batch`].
//!
//! Every request is checked in full before any environment changes, so a refused Reset or Step
//! leaves the session exactly as it was.

use serde::{Deserialize, Serialize};

use super::SessionError;
use crate::policy::{Planner, expert_action};
use crate::pools::{self, StepPool, Turn};
use crate::sim::{
    Config, Game, MAX_ARRIVALS, NUM_ACTIONS, OBSERVATION_SIZE, ResetInfo, StepOutcome, render,
    snapshot,
};

/// Kind tag of a whole-session snapshot (a single game's is `DDgm`).
const SESSION_SNAPSHOT: [u8; 4] = *b"DDss";

/// What a Step does to an environment whose episode has ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Autoreset {
    /// Gymnasium's default: the next Step resets it and ignores its action.
    NextStep,
    /// The Step that ends the episode resets it and reports the ended episode's last state.
    SameStep,
    /// Nothing: stepping it is an error until Reset.
    Disabled,
}

/// How a session was asked to behave, fixed at creation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SessionOptions {
    /// The autoreset mode.
    pub autoreset: Autoreset,
    /// Whether every Batch carries the action masks.
    pub action_masks: bool,
    /// Which expert's choices every Batch carries, if any.
    pub expert_actions: ExpertActions,
}

/// Which expert fills a Batch's `expert_actions`. Encoded like the `bool` it replaces (no, the
/// reference = 0, 1), so session snapshots written before the planner still restore.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ExpertActions {
    /// No expert actions.
    None,
    /// The reference heuristic's choices.
    Reference,
    /// The look-ahead planner's choices: 0.1-0.2 ms each, so Reset and Step of such a session run
    /// on the service's bounded CPU pool.
    Planner,
}

impl ExpertActions {
    /// Whether Batches carry expert actions at all.
    pub fn enabled(self) -> bool {
        self != ExpertActions::None
    }

    /// The chosen expert's action in `game`'s current state.
    fn choose(self, game: &Game) -> u8 {
        match self {
            ExpertActions::None => 0,
            ExpertActions::Reference => expert_action(game.restaurant()),
            ExpertActions::Planner => Planner::default().choose(game),
        }
    }
}

/// What a Reset asks for, as decoded from the request.
#[derive(Debug, Clone, Default)]
pub struct ResetArgs {
    /// Environment i is seeded `seed + i` (wrapping).
    pub seed: Option<u64>,
    /// One seed per environment; exclusive with `seed`.
    pub seeds: Vec<u64>,
    /// None, one list for all, or one per environment; `(customer_type, size)` pairs.
    pub arrivals: Vec<Vec<(u32, u32)>>,
    /// The configuration from this reset on.
    pub config: Option<Config>,
    /// Empty: reset every environment; else one flag per environment, at least one set, and the
    /// others keep their episode.
    pub reset_mask: Vec<bool>,
}

/// The result of a Reset or Step for all N environments, as packed little-endian arrays
/// (the layout of `dinerdash.v1.Batch`).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Batch {
    /// N.
    pub num_envs: u32,
    /// N x 40 int8.
    pub observations: Vec<u8>,
    /// N x int32.
    pub rewards: Vec<u8>,
    /// N x uint8.
    pub terminated: Vec<u8>,
    /// N x uint8.
    pub truncated: Vec<u8>,
    /// N x int32.
    pub scores: Vec<u8>,
    /// N x uint32.
    pub lost: Vec<u8>,
    /// N x uint32.
    pub ticks: Vec<u8>,
    /// N x 57 uint8, when the session asked for masks; else empty.
    pub action_masks: Vec<u8>,
    /// N x uint8, when the session asked for expert actions; else empty.
    pub expert_actions: Vec<u8>,
    /// N x uint8: the environment was reset in this call.
    pub reset: Vec<u8>,
    /// N: the seed of each environment reset in this call, else 0.
    pub seeds: Vec<u64>,
    /// N: resets of the stream since it was seeded, for environments reset in this call.
    pub stream_episodes: Vec<u32>,
    /// SAME_STEP Steps only: N x 40 int8 of the ended episodes (zeros elsewhere).
    pub final_observations: Vec<u8>,
    /// SAME_STEP Steps only: N x int32.
    pub final_scores: Vec<u8>,
    /// SAME_STEP Steps only: N x uint32.
    pub final_lost: Vec<u8>,
    /// SAME_STEP Steps only: N x uint32.
    pub final_ticks: Vec<u8>,
    /// SAME_STEP Steps with masks only: N x 57 uint8.
    pub final_action_masks: Vec<u8>,
    /// SAME_STEP Steps with expert actions only: N x uint8.
    pub final_expert_actions: Vec<u8>,
}

/// An i64 score as the int32 of the wire, saturated (scores stay far inside i32 in practice).
fn to_i32(v: i64) -> i32 {
    v.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
}

/// Writes `bytes` as row `i` of an array of rows of `W` bytes.
fn put<const W: usize>(array: &mut [u8], i: usize, bytes: [u8; W]) {
    array[i * W..][..W].copy_from_slice(&bytes);
}

/// Row `i` of an array of rows of `W` bytes, for the simulator to write the observation or the
/// mask into in place (an array returned and copied stalls on the store buffer).
fn row<const W: usize>(array: &mut [u8], i: usize) -> &mut [u8; W] {
    <&mut [u8; W]>::try_from(&mut array[i * W..][..W]).expect("a slice of W bytes")
}

/// The arrays that describe a state, row per environment: a Batch's current ones, or the
/// `final_*` ones of the episodes that ended (SAME_STEP).
struct StateRows<'a> {
    observations: &'a mut [u8],
    scores: &'a mut [u8],
    lost: &'a mut [u8],
    ticks: &'a mut [u8],
    action_masks: &'a mut [u8],
    expert_actions: &'a mut [u8],
}

impl StateRows<'_> {
    /// Writes `game`'s state as row `i`: observation, score, lost, tick, and the mask and expert
    /// action when the session asked for them.
    fn put(self, i: usize, game: &Game, options: &SessionOptions) {
        let r = game.restaurant();
        r.write_observation(row(self.observations, i), |v| v as u8);
        put(self.scores, i, to_i32(r.score()).to_le_bytes());
        put(self.lost, i, r.lost().to_le_bytes());
        put(self.ticks, i, r.tick().to_le_bytes());
        if options.action_masks {
            r.write_action_mask(row(self.action_masks, i));
        }
        if options.expert_actions.enabled() {
            self.expert_actions[i] = options.expert_actions.choose(game);
        }
    }
}

impl Batch {
    /// A batch of `n` environments, every array at its full length and zero: each environment's
    /// row is then written in place, whole arrays at a time. (Appending per element, with a
    /// capacity check each, cost about as much as computing the rows.)
    fn zeroed(n: usize, options: &SessionOptions, finals: bool) -> Batch {
        let finals_of = |width: usize| vec![0; if finals { n * width } else { 0 }];
        let mask_width = if options.action_masks { NUM_ACTIONS } else { 0 };
        let expert_width = usize::from(options.expert_actions.enabled());
        Batch {
            num_envs: n as u32,
            observations: vec![0; n * OBSERVATION_SIZE],
            rewards: vec![0; n * 4],
            terminated: vec![0; n],
            truncated: vec![0; n],
            scores: vec![0; n * 4],
            lost: vec![0; n * 4],
            ticks: vec![0; n * 4],
            action_masks: vec![0; n * mask_width],
            expert_actions: vec![0; n * expert_width],
            reset: vec![0; n],
            seeds: vec![0; n],
            stream_episodes: vec![0; n],
            final_observations: finals_of(OBSERVATION_SIZE),
            final_scores: finals_of(4),
            final_lost: finals_of(4),
            final_ticks: finals_of(4),
            final_action_masks: finals_of(mask_width),
            final_expert_actions: finals_of(expert_width),
        }
    }

    /// Every environment's rows, to be written in place (or cut into runs, one per chunk).
    fn rows(&mut self) -> Rows<'_> {
        Rows {
            n: self.num_envs as usize,
            observations: &mut self.observations,
            rewards: &mut self.rewards,
            terminated: &mut self.terminated,
            truncated: &mut self.truncated,
            scores: &mut self.scores,
            lost: &mut self.lost,
            ticks: &mut self.ticks,
            action_masks: &mut self.action_masks,
            expert_actions: &mut self.expert_actions,
            reset: &mut self.reset,
            seeds: &mut self.seeds,
            stream_episodes: &mut self.stream_episodes,
            final_observations: &mut self.final_observations,
            final_scores: &mut self.final_scores,
            final_lost: &mut self.final_lost,
            final_ticks: &mut self.final_ticks,
            final_action_masks: &mut self.final_action_masks,
            final_expert_actions: &mut self.final_expert_actions,
        }
    }

    /// How many environments were reset in this call.
    pub fn resets(&self) -> u64 {
        self.reset.iter().map(|&r| u64::from(r)).sum()
    }
}

/// The rows of a [`Batch`] that a run of consecutive environments writes: each array's slice
/// for them, indexed from the run's first environment. The runs of a parallel Step write
/// disjoint memory, so each chunk is stepped on its own thread with no lock.
struct Rows<'a> {
    /// Environments in the run.
    n: usize,
    /// N x 40 int8.
    observations: &'a mut [u8],
    /// N x int32.
    rewards: &'a mut [u8],
    /// N x uint8.
    terminated: &'a mut [u8],
    /// N x uint8.
    truncated: &'a mut [u8],
    /// N x int32.
    scores: &'a mut [u8],
    /// N x uint32.
    lost: &'a mut [u8],
    /// N x uint32.
    ticks: &'a mut [u8],
    /// N x 57 uint8, or empty.
    action_masks: &'a mut [u8],
    /// N x uint8, or empty.
    expert_actions: &'a mut [u8],
    /// N x uint8.
    reset: &'a mut [u8],
    /// N.
    seeds: &'a mut [u64],
    /// N.
    stream_episodes: &'a mut [u32],
    /// N x 40 int8, or empty.
    final_observations: &'a mut [u8],
    /// N x int32, or empty.
    final_scores: &'a mut [u8],
    /// N x uint32, or empty.
    final_lost: &'a mut [u8],
    /// N x uint32, or empty.
    final_ticks: &'a mut [u8],
    /// N x 57 uint8, or empty.
    final_action_masks: &'a mut [u8],
    /// N x uint8, or empty.
    final_expert_actions: &'a mut [u8],
}

/// `array`, rows of `array.len() / n` elements for `n` environments, cut after `k` of them.
fn cut<T>(array: &mut [T], n: usize, k: usize) -> (&mut [T], &mut [T]) {
    let width = array.len() / n.max(1);
    array.split_at_mut(width * k)
}

impl<'a> Rows<'a> {
    /// The first `k` environments' rows and the others'.
    fn split_at(self, k: usize) -> (Rows<'a>, Rows<'a>) {
        let n = self.n;
        macro_rules! split {
            ($($field:ident),*) => {{
                $(let $field = cut(self.$field, n, k);)*
                (
                    Rows { n: k, $($field: $field.0,)* },
                    Rows { n: n - k, $($field: $field.1,)* },
                )
            }};
        }
        split!(
            observations,
            rewards,
            terminated,
            truncated,
            scores,
            lost,
            ticks,
            action_masks,
            expert_actions,
            reset,
            seeds,
            stream_episodes,
            final_observations,
            final_scores,
            final_lost,
            final_ticks,
            final_action_masks,
            final_expert_actions
        )
    }

    /// Writes environment `i`'s row: what happened in this call, then the state it is in now.
    fn put(
        &mut self,
        i: usize,
        outcome: StepOutcome,
        reset: Option<ResetInfo>,
        game: &Game,
        options: &SessionOptions,
    ) {
        put(self.rewards, i, to_i32(outcome.reward).to_le_bytes());
        self.terminated[i] = u8::from(outcome.terminated);
        self.truncated[i] = u8::from(outcome.truncated);
        if let Some(info) = reset {
            self.reset[i] = 1;
            self.seeds[i] = info.seed;
            self.stream_episodes[i] = info.stream_episodes;
        }
        let now = StateRows {
            observations: self.observations,
            scores: self.scores,
            lost: self.lost,
            ticks: self.ticks,
            action_masks: self.action_masks,
            expert_actions: self.expert_actions,
        };
        now.put(i, game, options);
    }

    /// Environment `i` was just reset: reward 0, not done.
    fn put_reset(&mut self, i: usize, info: ResetInfo, game: &Game, options: &SessionOptions) {
        let nothing = StepOutcome::default();
        self.put(i, nothing, Some(info), game, options);
    }

    /// A partial Reset left environment `i` alone: its current state, reward 0.
    fn put_unchanged(&mut self, i: usize, game: &Game, options: &SessionOptions) {
        let r = game.restaurant();
        let state = StepOutcome {
            reward: 0,
            terminated: r.is_terminated(),
            truncated: r.is_truncated(),
        };
        self.put(i, state, None, game, options);
    }

    /// Writes environment `i`'s ended episode (SAME_STEP); the rows of the others stay zero.
    fn put_final(&mut self, i: usize, ended: &Game, options: &SessionOptions) {
        let finals = StateRows {
            observations: self.final_observations,
            scores: self.final_scores,
            lost: self.final_lost,
            ticks: self.final_ticks,
            action_masks: self.final_action_masks,
            expert_actions: self.final_expert_actions,
        };
        finals.put(i, ended, options);
    }
}

/// A run of consecutive environments with their rows and actions: what one chunk of a Reset or
/// Step works on.
struct Run<'a> {
    /// Index in the session of the run's first environment.
    first: usize,
    /// The environments.
    envs: &'a mut [Env],
    /// Their rows of the Batch.
    rows: Rows<'a>,
    /// Their actions, 4 bytes each (a Step's; empty for a Reset).
    actions: &'a [u8],
}

impl<'a> Run<'a> {
    /// The whole session as one run.
    fn whole(envs: &'a mut [Env], batch: &'a mut Batch, actions: &'a [u8]) -> Run<'a> {
        Run {
            first: 0,
            envs,
            rows: batch.rows(),
            actions,
        }
    }

    /// The run cut into `chunks` runs of sizes differing by at most one, in order.
    fn cut(self, chunks: usize) -> Vec<Run<'a>> {
        let n = self.envs.len();
        let chunks = chunks.clamp(1, n.max(1));
        let mut runs = Vec::with_capacity(chunks);
        let mut rest = self;
        for c in 0..chunks {
            let k = n / chunks + usize::from(c < n % chunks);
            let Run {
                first,
                envs,
                rows,
                actions,
            } = rest;
            let (envs, more_envs) = envs.split_at_mut(k);
            let (rows, more_rows) = rows.split_at(k);
            let (actions, more_actions) = actions.split_at((4 * k).min(actions.len()));
            runs.push(Run {
                first,
                envs,
                rows,
                actions,
            });
            rest = Run {
                first: first + k,
                envs: more_envs,
                rows: more_rows,
                actions: more_actions,
            };
        }
        runs
    }
}

/// One environment: a game, and whether the next Step resets it.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct Env {
    /// The game, random stream included.
    game: Game,
    /// NEXT_STEP: the episode ended in the last Step, so the next Step resets it.
    autoreset_pending: bool,
}

impl Env {
    /// Whether the current episode has ended.
    fn done(&self) -> bool {
        let r = self.game.restaurant();
        r.is_terminated() || r.is_truncated()
    }
}

/// The N environments of a session and its options: everything a snapshot holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Envs {
    /// At least one.
    envs: Vec<Env>,
    /// Fixed at creation.
    options: SessionOptions,
    /// The seed of CreateSession, used by the first Reset if that gives none.
    first_seed: Option<u64>,
}

impl Envs {
    /// What one environment holds: a game is plain fixed-size data (random stream included), so
    /// this is all of it; the memory budget charges sessions by it.
    pub const BYTES_PER_ENV: u64 = std::mem::size_of::<Env>() as u64;

    /// `n >= 1` environments with `config`, not reset yet.
    pub fn new(
        n: usize,
        config: Config,
        options: SessionOptions,
        seed: Option<u64>,
    ) -> Result<Envs, SessionError> {
        let game = Game::new(config).map_err(|e| SessionError::InvalidArgument(e.to_string()))?;
        let env = Env {
            game,
            autoreset_pending: false,
        };
        Ok(Envs {
            envs: vec![env; n],
            options,
            first_seed: seed,
        })
    }

    /// N.
    pub fn len(&self) -> usize {
        self.envs.len()
    }

    /// Never: a session holds at least one environment.
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// The options fixed at creation.
    pub fn options(&self) -> &SessionOptions {
        &self.options
    }

    /// Environment `index`'s game, once it has been reset.
    pub fn restaurant(&self, index: usize) -> Option<&crate::sim::Restaurant> {
        let game = &self.envs.get(index)?.game;
        game.is_started().then(|| game.restaurant())
    }

    /// The configuration the next reset uses.
    pub fn config(&self) -> Config {
        self.envs
            .first()
            .map_or_else(Config::default, |e| *e.game.config())
    }

    /// Resets every environment, or those of `reset_mask` (all of the request is checked first),
    /// on the caller's thread.
    pub fn reset(&mut self, args: &ResetArgs) -> Result<Batch, SessionError> {
        self.reset_on(args, &pools::SERIAL, Turn::default())
    }

    /// [`Envs::reset`], in chunks on `pool`'s threads in `turn` when the session is large enough
    /// for it: the same Batch and the same environments after it as on one thread.
    pub fn reset_on(
        &mut self,
        args: &ResetArgs,
        pool: &StepPool,
        turn: Turn,
    ) -> Result<Batch, SessionError> {
        let n = self.envs.len();
        let invalid = |msg: String| Err(SessionError::InvalidArgument(msg));
        if args.seed.is_some() && !args.seeds.is_empty() {
            return invalid("seed and seeds are exclusive: give at most one".into());
        }
        if !args.seeds.is_empty() && args.seeds.len() != n {
            return invalid(format!(
                "seeds must hold 0 or {n} entries (one per environment), got {}",
                args.seeds.len()
            ));
        }
        if ![0, 1, n].contains(&args.arrivals.len()) {
            return invalid(format!(
                "arrivals must hold 0, 1 or {n} lists, got {}",
                args.arrivals.len()
            ));
        }
        for (i, list) in args.arrivals.iter().enumerate() {
            check_arrivals(i, list)?;
        }
        if let Some(config) = &args.config {
            config
                .validate()
                .map_err(|e| SessionError::InvalidArgument(e.to_string()))?;
        }
        let partial = !args.reset_mask.is_empty();
        if partial {
            if args.reset_mask.len() != n {
                return invalid(format!(
                    "reset_mask must hold 0 or {n} entries (one per environment), got {}",
                    args.reset_mask.len()
                ));
            }
            if !args.reset_mask.contains(&true) {
                return invalid("reset_mask selects no environment".into());
            }
            if args.config.is_some() {
                return invalid(
                    "config applies to every environment: give it with a full reset, not a reset_mask"
                        .into(),
                );
            }
            let mut kept = args.reset_mask.iter().zip(&self.envs);
            if let Some(i) = kept.position(|(&reset, env)| !reset && !env.game.is_started()) {
                return Err(SessionError::KeptNeverReset(i));
            }
        }

        let first_seed = self.first_seed.take();
        let base = args.seed.or(if args.seeds.is_empty() {
            first_seed
        } else {
            None
        });
        let options = self.options;
        let mut batch = Batch::zeroed(n, &options, false);
        let whole = Run::whole(&mut self.envs, &mut batch, &[]);
        let work = |run: Run<'_>| reset_run(run, args, base, &options);
        let planner = options.expert_actions == ExpertActions::Planner;
        let chunks = pool.chunks(n, planner);
        if chunks <= 1 {
            work(whole)?;
        } else {
            if planner {
                pool.run(turn, whole.cut(chunks), work)?;
            } else {
                pool.run_first_come(whole.cut(chunks), work)?;
            }
        }
        Ok(batch)
    }

    /// One action per environment, as N little-endian int32 (all checked first), on the
    /// caller's thread.
    pub fn step(&mut self, actions: &[u8]) -> Result<Batch, SessionError> {
        self.step_on(actions, &pools::SERIAL, Turn::default())
    }

    /// [`Envs::step`], in chunks on `pool`'s threads in `turn` when the session is large enough
    /// for it: the same Batch and the same environments after it as on one thread.
    pub fn step_on(
        &mut self,
        actions: &[u8],
        pool: &StepPool,
        turn: Turn,
    ) -> Result<Batch, SessionError> {
        let n = self.envs.len();
        if actions.len() != 4 * n {
            return Err(SessionError::InvalidArgument(format!(
                "actions must hold {n} little-endian int32 ({} bytes), got {} bytes",
                4 * n,
                actions.len()
            )));
        }
        for (i, a) in actions.chunks_exact(4).enumerate() {
            let a = i32::from_le_bytes([a[0], a[1], a[2], a[3]]);
            if !(0..NUM_ACTIONS as i32).contains(&a) {
                return Err(SessionError::ActionOutOfRange { env: i, action: a });
            }
        }
        if !self.envs.iter().all(|e| e.game.is_started()) {
            return Err(SessionError::NotReset);
        }
        let mode = self.options.autoreset;
        if mode == Autoreset::Disabled {
            if let Some(i) = self.envs.iter().position(Env::done) {
                return Err(if n == 1 {
                    SessionError::EpisodeOver
                } else {
                    SessionError::EnvEpisodeOver(i)
                });
            }
        }

        let options = self.options;
        let mut batch = Batch::zeroed(n, &options, mode == Autoreset::SameStep);
        let whole = Run::whole(&mut self.envs, &mut batch, actions);
        let work = |run: Run<'_>| step_run(run, &options);
        let planner = options.expert_actions == ExpertActions::Planner;
        let chunks = pool.chunks(n, planner);
        if chunks <= 1 {
            work(whole)?;
        } else {
            if planner {
                pool.run(turn, whole.cut(chunks), work)?;
            } else {
                pool.run_first_come(whole.cut(chunks), work)?;
            }
        }
        Ok(batch)
    }

    /// Environment `index` drawn as text.
    pub fn render(&self, index: u32, color: bool) -> Result<String, SessionError> {
        let n = self.envs.len();
        let env = usize::try_from(index)
            .ok()
            .and_then(|i| self.envs.get(i))
            .ok_or_else(|| {
                SessionError::InvalidArgument(format!(
                    "env_index must be in 0..={}, got {index}",
                    n - 1
                ))
            })?;
        if !env.game.is_started() {
            return Err(SessionError::NotReset);
        }
        Ok(render::render(env.game.restaurant(), color))
    }

    /// The whole session as versioned bytes.
    pub fn snapshot(&self) -> Vec<u8> {
        snapshot::encode(SESSION_SNAPSHOT, self)
    }

    /// Environments `start..start + count` (`count` 0: to the end) as the versioned bytes of a
    /// session of their own, each exactly as it is here; Restore makes that session.
    pub fn snapshot_range(&self, start: u32, count: u32) -> Result<Vec<u8>, SessionError> {
        let n = self.envs.len();
        let (start, count) = (start as usize, count as usize);
        let stop = if count == 0 {
            n
        } else {
            start.saturating_add(count)
        };
        if start == 0 && stop == n {
            return Ok(self.snapshot());
        }
        if start >= stop || stop > n {
            return Err(SessionError::InvalidArgument(format!(
                "snapshot range: env_start {start} and env_count {count} must name environments \
                 of 0..{n}"
            )));
        }
        let part = Envs {
            envs: self.envs[start..stop].to_vec(),
            options: self.options,
            first_seed: self.first_seed.map(|s| s.wrapping_add(start as u64)),
        };
        Ok(part.snapshot())
    }

    /// How many environments [`Envs::snapshot`] bytes hold, read from their header without
    /// decoding any (`envs` is the first field): 1..=`max_envs`, else refused.
    pub fn count(bytes: &[u8], max_envs: usize) -> Result<usize, SessionError> {
        let n = snapshot::leading_count(SESSION_SNAPSHOT, bytes).map_err(corrupt_snapshot)?;
        if !(1..=max_envs as u64).contains(&n) {
            return Err(SessionError::InvalidArgument(format!(
                "snapshot: the number of environments must be in 1..={max_envs}, got {n}"
            )));
        }
        // At most `max_envs`, a usize.
        Ok(n as usize)
    }

    /// A session from [`Envs::snapshot`] bytes, checked: at most `max_envs` environments (their
    /// [`Envs::count`], before any is decoded), every game a reachable state.
    pub fn restore(bytes: &[u8], max_envs: usize) -> Result<Envs, SessionError> {
        Envs::count(bytes, max_envs)?;
        let mut envs: Envs = snapshot::decode(SESSION_SNAPSHOT, bytes).map_err(corrupt_snapshot)?;
        for (i, env) in envs.envs.iter().enumerate() {
            env.game.check().map_err(|e| {
                SessionError::InvalidArgument(format!("snapshot: environment {i}: {e}"))
            })?;
        }
        // Only an ended NEXT_STEP episode can be waiting for its autoreset.
        let next_step = envs.options.autoreset == Autoreset::NextStep;
        for env in &mut envs.envs {
            env.autoreset_pending = next_step && env.done();
        }
        Ok(envs)
    }
}

/// The refusal of snapshot bytes that do not decode.
fn corrupt_snapshot(e: snapshot::SnapshotError) -> SessionError {
    SessionError::InvalidArgument(format!("snapshot: {e}"))
}

/// Resets the environments of `run` as `args` asks (`base`: the seed of the session's first
/// environment, if any), writing their rows; the request was checked in full.
fn reset_run(
    run: Run<'_>,
    args: &ResetArgs,
    base: Option<u64>,
    options: &SessionOptions,
) -> Result<(), SessionError> {
    let Run {
        first,
        envs,
        mut rows,
        ..
    } = run;
    let partial = !args.reset_mask.is_empty();
    for (j, env) in envs.iter_mut().enumerate() {
        let i = first + j;
        if partial && !args.reset_mask[i] {
            rows.put_unchanged(j, &env.game, options);
            continue;
        }
        if let Some(config) = args.config {
            env.game.set_config(config).map_err(internal)?;
        }
        let seed = match args.seeds.get(i) {
            Some(&s) => Some(s),
            None => base.map(|s| s.wrapping_add(i as u64)),
        };
        // A game never seeded gets a fresh seed of its own, reported in the Batch.
        let seed = seed.or_else(|| (!env.game.is_seeded()).then(entropy_seed));
        let arrivals = match args.arrivals.len() {
            0 => None,
            1 => args.arrivals.first(),
            _ => args.arrivals.get(i),
        };
        let info = env
            .game
            .reset(seed, arrivals.map(Vec::as_slice))
            .map_err(internal)?;
        env.autoreset_pending = false;
        rows.put_reset(j, info, &env.game, options);
    }
    Ok(())
}

/// Steps the environments of `run` with their actions (checked), writing their rows.
fn step_run(run: Run<'_>, options: &SessionOptions) -> Result<(), SessionError> {
    let Run {
        envs,
        mut rows,
        actions,
        ..
    } = run;
    let mode = options.autoreset;
    for (i, (env, a)) in envs.iter_mut().zip(actions.chunks_exact(4)).enumerate() {
        let action = i64::from(i32::from_le_bytes([a[0], a[1], a[2], a[3]]));
        if env.autoreset_pending {
            // NEXT_STEP: this Step resets the environment and ignores its action.
            let info = env.game.reset(None, None).map_err(internal)?;
            env.autoreset_pending = false;
            rows.put_reset(i, info, &env.game, options);
            continue;
        }
        let outcome = env.game.step(action).map_err(internal)?;
        let ended = outcome.terminated || outcome.truncated;
        let mut reset = None;
        match mode {
            Autoreset::NextStep => env.autoreset_pending = ended,
            Autoreset::SameStep if ended => {
                rows.put_final(i, &env.game, options);
                reset = Some(env.game.reset(None, None).map_err(internal)?);
            }
            Autoreset::SameStep | Autoreset::Disabled => {}
        }
        rows.put(i, outcome, reset, &env.game, options);
    }
    Ok(())
}

/// A seed for a game that was never given one: 63 bits of system entropy. Drawn here, above
/// the simulator, which stays pure.
fn entropy_seed() -> u64 {
    use rand::TryRngCore;
    let bits = rand::rngs::OsRng.try_next_u64().unwrap_or_else(|_| {
        // No OS entropy: the clock still gives distinct seeds, and the seed is reported anyway.
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(0)
    });
    bits >> 1
}

/// Checks explicit arrival list `i` of a Reset.
fn check_arrivals(i: usize, list: &[(u32, u32)]) -> Result<(), SessionError> {
    if !(1..=MAX_ARRIVALS).contains(&list.len()) {
        return Err(SessionError::InvalidArgument(format!(
            "arrivals[{i}] must hold 1..={MAX_ARRIVALS} groups, got {}",
            list.len()
        )));
    }
    for (g, &(customer_type, size)) in list.iter().enumerate() {
        if !(1..=2).contains(&customer_type) {
            return Err(SessionError::InvalidArgument(format!(
                "arrivals[{i}].groups[{g}].customer_type must be in 1..=2, got {customer_type}"
            )));
        }
        if !(1..=6).contains(&size) {
            return Err(SessionError::InvalidArgument(format!(
                "arrivals[{i}].groups[{g}].size must be in 1..=6, got {size}"
            )));
        }
    }
    Ok(())
}

/// An error the checks above rule out; reported rather than panicking.
fn internal(e: impl std::fmt::Display) -> SessionError {
    SessionError::Internal(e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(autoreset: Autoreset) -> SessionOptions {
        SessionOptions {
            autoreset,
            action_masks: true,
            expert_actions: ExpertActions::Reference,
        }
    }

    fn actions(a: &[i32]) -> Vec<u8> {
        a.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn refused_requests_change_nothing() {
        let mut envs =
            Envs::new(2, Config::default(), options(Autoreset::NextStep), Some(3)).unwrap();
        envs.reset(&ResetArgs::default()).unwrap();
        let before = envs.snapshot();
        assert!(envs.step(&actions(&[0, 57])).is_err());
        let bad = ResetArgs {
            arrivals: vec![vec![(1, 1)], vec![(1, 7)]],
            ..ResetArgs::default()
        };
        assert_eq!(
            envs.reset(&bad).unwrap_err().to_string(),
            "arrivals[1].groups[0].size must be in 1..=6, got 7"
        );
        assert_eq!(envs.snapshot(), before);
    }

    #[test]
    fn first_reset_uses_the_creation_seed_per_environment() {
        let mut envs =
            Envs::new(3, Config::default(), options(Autoreset::NextStep), Some(10)).unwrap();
        let batch = envs.reset(&ResetArgs::default()).unwrap();
        assert_eq!(batch.seeds, vec![10, 11, 12]);
        let again = envs.reset(&ResetArgs::default()).unwrap();
        assert_eq!(again.seeds, vec![10, 11, 12]);
        assert_eq!(again.stream_episodes, vec![1, 1, 1]);
    }

    #[test]
    fn a_reset_mask_resets_only_its_environments() {
        let mut envs = Envs::new(3, Config::default(), options(Autoreset::Disabled), None).unwrap();
        let refused = |envs: &mut Envs, mask: &[bool], config: Option<Config>| {
            let args = ResetArgs {
                reset_mask: mask.to_vec(),
                config,
                ..ResetArgs::default()
            };
            envs.reset(&args).unwrap_err().to_string()
        };
        assert_eq!(
            refused(&mut envs, &[true, false, true], None),
            "environment 1 has never been reset: include it in reset_mask"
        );
        envs.reset(&ResetArgs {
            seed: Some(5),
            ..ResetArgs::default()
        })
        .unwrap();
        let before = envs.step(&actions(&[0, 0, 0])).unwrap();
        assert_eq!(
            refused(&mut envs, &[true, false], None),
            "reset_mask must hold 0 or 3 entries (one per environment), got 2"
        );
        assert_eq!(
            refused(&mut envs, &[false; 3], None),
            "reset_mask selects no environment"
        );
        assert_eq!(
            refused(&mut envs, &[true; 3], Some(Config::default())),
            "config applies to every environment: give it with a full reset, not a reset_mask"
        );

        let partial = envs
            .reset(&ResetArgs {
                seed: Some(100),
                reset_mask: vec![false, true, false],
                ..ResetArgs::default()
            })
            .unwrap();
        assert_eq!(partial.reset, vec![0, 1, 0]);
        assert_eq!(partial.seeds, vec![0, 101, 0]);
        let row = |b: &Batch, i: usize| {
            b.observations[i * OBSERVATION_SIZE..][..OBSERVATION_SIZE].to_vec()
        };
        for i in [0, 2] {
            assert_eq!(row(&partial, i), row(&before, i));
        }
        assert_eq!(partial.ticks[..4], before.ticks[..4]);
        let mut fresh =
            Envs::new(1, Config::default(), options(Autoreset::Disabled), None).unwrap();
        let fresh = fresh
            .reset(&ResetArgs {
                seed: Some(101),
                ..ResetArgs::default()
            })
            .unwrap();
        assert_eq!(row(&partial, 1), row(&fresh, 0));
        assert_eq!(partial.expert_actions[1], fresh.expert_actions[0]);
        assert_eq!(partial.ticks[4..8], [0; 4]);
    }

    #[test]
    fn snapshot_round_trips() {
        let mut envs =
            Envs::new(2, Config::default(), options(Autoreset::SameStep), Some(1)).unwrap();
        envs.reset(&ResetArgs::default()).unwrap();
        envs.step(&actions(&[15, 16])).unwrap();
        let bytes = envs.snapshot();
        let mut copy = Envs::restore(&bytes, 8).unwrap();
        assert_eq!(copy.step(&actions(&[0, 0])), envs.step(&actions(&[0, 0])));
        assert!(Envs::restore(&bytes, 1).is_err());
        assert!(Envs::restore(&bytes[..bytes.len() - 3], 8).is_err());
    }

    #[test]
    fn a_range_restores_as_a_session_of_its_own() {
        let mut envs =
            Envs::new(4, Config::default(), options(Autoreset::NextStep), Some(7)).unwrap();
        envs.reset(&ResetArgs::default()).unwrap();
        envs.step(&actions(&[15, 16, 17, 18])).unwrap();
        let mut middle = Envs::restore(&envs.snapshot_range(1, 2).unwrap(), 8).unwrap();
        let mut tail = Envs::restore(&envs.snapshot_range(3, 0).unwrap(), 8).unwrap();
        assert_eq!((middle.len(), tail.len()), (2, 1));
        let whole = envs.step(&actions(&[0, 1, 2, 3])).unwrap();
        let (m, t) = (
            middle.step(&actions(&[1, 2])).unwrap(),
            tail.step(&actions(&[3])).unwrap(),
        );
        assert_eq!(
            m.observations,
            whole.observations[OBSERVATION_SIZE..3 * OBSERVATION_SIZE]
        );
        assert_eq!(t.observations, whole.observations[3 * OBSERVATION_SIZE..]);
        assert_eq!(envs.snapshot_range(0, 0).unwrap(), envs.snapshot());
        for (start, count) in [(4, 0), (3, 2), (5, 1)] {
            assert!(
                envs.snapshot_range(start, count).is_err(),
                "{start} {count}"
            );
        }
    }
}
