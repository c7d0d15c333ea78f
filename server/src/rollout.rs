//! The Rollout RPC's rules and recorder: what a request may ask for ([`RolloutPlan`]) and what
//! its stream is charged, and the recording of whole episodes of a server-side policy: the reset
//! observation, then per step the expert's choice in the state before it, the action, the reward
//! and the new observation. Recording is synchronous and CPU-bound: the service runs it on its
//! CPU pool, in chunks of [`ROLLOUT_CHUNK`] ([`Recorder`]) so that no episode holds a worker
//! while other tenants wait.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::budget::{Budget, BudgetError, Charge, Tenant};
use crate::policy::{Policy, PolicyKind, expert_action};
use crate::sim::{Config, ConfigError, Game, NUM_ACTIONS, OBSERVATION_SIZE};

/// Most steps of one recorded episode: bounds the size of one streamed message (~10 MB).
pub const MAX_ROLLOUT_STEPS: u32 = 100_000;
/// Most episodes one Rollout request may ask for.
pub const MAX_ROLLOUT_EPISODES: u32 = 10_000;
/// Default most steps one Rollout request may record over all its episodes (~1 GB of output,
/// seconds to minutes of a worker): the request's work cap ([`Limits::max_work_steps`]). 10,000
/// seeds of no-decay games would otherwise ask for ~10^9 steps.
pub const MAX_ROLLOUT_WORK_STEPS: u64 = 10_000_000;
/// Bytes one recorded step takes at most: observation, action, reward, expert action, mask.
pub const MAX_BYTES_PER_STEP: u64 = (OBSERVATION_SIZE + 1 + 4 + 1 + NUM_ACTIONS) as u64;

/// How long a Rollout plays on a worker before it gives the worker back and waits for its next
/// turn ([`crate::pools::CpuPool`]): what another tenant's planner Step may wait for it.
pub const ROLLOUT_CHUNK: Duration = Duration::from_millis(20);

/// Rollout episodes recorded ahead of the reader: one, so that a stream is produced on demand.
pub const ROLLOUT_BUFFER: usize = 1;
/// Episodes a Rollout stream may hold at once, for the memory budget: the one buffered, one in
/// the transport's send buffer, and the one being recorded.
const ROLLOUT_EPISODES_HELD: u64 = ROLLOUT_BUFFER as u64 + 2;

/// What a server lets one Rollout request do (`--max-rollout-work-steps`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Most steps one Rollout request may record over all its episodes (its work cap).
    pub max_work_steps: u64,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_work_steps: MAX_ROLLOUT_WORK_STEPS,
        }
    }
}

/// Why a Rollout request is refused before anything is recorded; the service maps each to its
/// status once ([`crate::service::status`](mod@crate::service::status)).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RolloutError {
    /// A field is out of range; the message starts with the field's name (`seeds`, `max_steps`,
    /// a configuration field) and gives its allowed range.
    #[error("{0}")]
    InvalidArgument(String),
    /// The memory budget or the tenant's share of Rollout streams would be passed.
    #[error(transparent)]
    OverBudget(#[from] BudgetError),
}

/// A Rollout request that passed its checks: what its stream records.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RolloutPlan {
    /// Who plays.
    pub policy: PolicyKind,
    /// One episode per seed, in order.
    pub seeds: Vec<u64>,
    /// Most steps of each episode.
    pub max_steps: u32,
    /// The game.
    pub config: Config,
    /// Whether episodes carry action masks.
    pub action_masks: bool,
}

impl RolloutPlan {
    /// Checks a request: 1..=[`MAX_ROLLOUT_EPISODES`] seeds, `max_steps` in
    /// 1..=[`MAX_ROLLOUT_STEPS`] (absent: the most), a valid configuration.
    pub fn new(
        policy: PolicyKind,
        seeds: Vec<u64>,
        max_steps: Option<u32>,
        config: Config,
        action_masks: bool,
    ) -> Result<RolloutPlan, RolloutError> {
        let invalid = RolloutError::InvalidArgument;
        if seeds.is_empty() || seeds.len() > MAX_ROLLOUT_EPISODES as usize {
            return Err(invalid(format!(
                "seeds must hold 1..={MAX_ROLLOUT_EPISODES} seeds, got {}",
                seeds.len()
            )));
        }
        let max_steps = max_steps.unwrap_or(MAX_ROLLOUT_STEPS);
        if !(1..=MAX_ROLLOUT_STEPS).contains(&max_steps) {
            return Err(invalid(format!(
                "max_steps must be in 1..={MAX_ROLLOUT_STEPS}, got {max_steps}"
            )));
        }
        config.validate().map_err(|e| invalid(e.to_string()))?;
        Ok(RolloutPlan {
            policy,
            seeds,
            max_steps,
            config,
            action_masks,
        })
    }

    /// Bytes the memory budget charges the stream: the episodes it may hold at once, each of
    /// `max_steps` steps at the most a step may take.
    pub fn bytes(&self) -> u64 {
        let episode_bytes = (u64::from(self.max_steps) + 1) * MAX_BYTES_PER_STEP;
        ROLLOUT_EPISODES_HELD * episode_bytes
    }

    /// Charges the stream to `tenant` in `budget` (its bytes and one of the tenant's Rollout
    /// streams), before anything is recorded; the charge is given back when dropped.
    pub fn charge(
        &self,
        budget: &Arc<Budget>,
        tenant: &Arc<Tenant>,
    ) -> Result<Charge, RolloutError> {
        Ok(budget.charge_rollout(tenant, self.bytes())?)
    }
}

/// One recorded episode, in the packed layout of `dinerdash.v1.Episode`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Recording {
    /// The reset seed.
    pub seed: u64,
    /// Steps taken, T.
    pub steps: u32,
    /// (T + 1) x 40 int8.
    pub observations: Vec<u8>,
    /// T x uint8.
    pub actions: Vec<u8>,
    /// T x int32 little-endian.
    pub rewards: Vec<u8>,
    /// T x uint8: the expert's choice in the state before each step.
    pub expert_actions: Vec<u8>,
    /// (T + 1) x 57 uint8 when asked for, else empty.
    pub action_masks: Vec<u8>,
    /// Final score.
    pub score: i64,
    /// Groups lost.
    pub lost: u32,
    /// Ended by losing groups.
    pub terminated: bool,
    /// Ended by the time limit or `max_steps`.
    pub truncated: bool,
}

/// Plays `policy` from `reset(seed)` until the episode ends or `max_steps` steps pass.
pub fn record(
    policy: PolicyKind,
    config: Config,
    seed: u64,
    max_steps: u32,
    action_masks: bool,
) -> Result<Recording, ConfigError> {
    let never = AtomicBool::new(false);
    record_until(policy, config, seed, max_steps, action_masks, &never)
        .map(Option::unwrap_or_default)
}

/// [`record`], abandoned (`Ok(None)`) as soon as `stop` is set: checked every step, so a
/// cancelled request frees its worker within microseconds, not after a whole episode.
pub fn record_until(
    policy: PolicyKind,
    config: Config,
    seed: u64,
    max_steps: u32,
    action_masks: bool,
    stop: &AtomicBool,
) -> Result<Option<Recording>, ConfigError> {
    let mut recorder = Recorder::new(policy, config, seed, max_steps, action_masks)?;
    Ok(match recorder.play(None, stop) {
        Played::Stopped => None,
        Played::Ended | Played::Paused => Some(recorder.finish()),
    })
}

/// Where [`Recorder::play`] stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Played {
    /// The episode ended (the game, or `max_steps`): [`Recorder::finish`] it.
    Ended,
    /// Its time was up: play on later, on any thread.
    Paused,
    /// The stop flag was set: abandon it.
    Stopped,
}

/// One episode being recorded, played in as many chunks as its caller likes: between them it
/// holds no thread, so a worker can serve others' jobs meanwhile. The chunks' cut changes
/// nothing of the episode.
pub struct Recorder {
    /// The game played.
    game: Game,
    /// Who plays.
    player: Box<dyn Policy + Send>,
    /// Which policy `player` is (the expert's choice is reused rather than asked twice).
    policy: PolicyKind,
    /// What is recorded so far.
    rec: Recording,
    /// Most steps of the episode.
    max_steps: u32,
    /// Whether states carry action masks.
    action_masks: bool,
    /// Whether the game ended it.
    ended: bool,
}

impl Recorder {
    /// An episode of `policy` from `reset(seed)`, its reset state recorded.
    pub fn new(
        policy: PolicyKind,
        config: Config,
        seed: u64,
        max_steps: u32,
        action_masks: bool,
    ) -> Result<Recorder, ConfigError> {
        let mut game = Game::new(config)?;
        // A drawn arrival list cannot be refused.
        let _ = game.reset(Some(seed), None);
        let mut rec = Recording {
            seed,
            ..Recording::default()
        };
        rec.observations.reserve(OBSERVATION_SIZE * 600);
        if action_masks {
            rec.action_masks.reserve(NUM_ACTIONS * 600);
        }
        let mut recorder = Recorder {
            game,
            player: policy.build(seed),
            policy,
            rec,
            max_steps,
            action_masks,
            ended: false,
        };
        recorder.push_state();
        Ok(recorder)
    }

    /// Records the game's state: its observation, and its action mask when asked for.
    fn push_state(&mut self) {
        let r = self.game.restaurant();
        self.rec
            .observations
            .extend(r.observation().iter().map(|&v| v as u8));
        if self.action_masks {
            self.rec
                .action_masks
                .extend(r.action_mask().iter().map(|&m| u8::from(m)));
        }
    }

    /// Plays until the episode ends, `stop` is set (checked before every step), or `until`
    /// passes (checked after every step, so that each chunk plays at least one).
    pub fn play(&mut self, until: Option<Instant>, stop: &AtomicBool) -> Played {
        while self.rec.steps < self.max_steps && !self.ended {
            if stop.load(Ordering::Relaxed) {
                return Played::Stopped;
            }
            let expert = expert_action(self.game.restaurant());
            let action = match self.policy {
                // The expert's choice is already known; asking again would repeat the
                // look-ahead.
                PolicyKind::Expert => expert,
                PolicyKind::Random | PolicyKind::Planner => self.player.act(&self.game),
            };
            let Ok(outcome) = self.game.step(i64::from(action)) else {
                // A refused step ends the episode as `max_steps` would: truncated.
                self.max_steps = self.rec.steps;
                break;
            };
            let rec = &mut self.rec;
            rec.steps += 1;
            rec.expert_actions.push(expert);
            rec.actions.push(action);
            let reward = outcome
                .reward
                .clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32;
            rec.rewards.extend_from_slice(&reward.to_le_bytes());
            rec.terminated = outcome.terminated;
            rec.truncated = outcome.truncated;
            self.ended = outcome.terminated || outcome.truncated;
            self.push_state();
            if until.is_some_and(|until| Instant::now() >= until) {
                break;
            }
        }
        if self.ended || self.rec.steps >= self.max_steps {
            Played::Ended
        } else {
            Played::Paused
        }
    }

    /// The recording of an episode [`Recorder::play`] ended.
    pub fn finish(mut self) -> Recording {
        if !self.ended {
            self.rec.truncated = true;
        }
        let r = self.game.restaurant();
        self.rec.score = r.score();
        self.rec.lost = r.lost();
        self.rec
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::run_episode;

    #[test]
    fn recordings_agree_with_eval() {
        for policy in [PolicyKind::Expert, PolicyKind::Random] {
            let rec = record(policy, Config::default(), 4, 100_000, true).unwrap();
            let summary = run_episode(policy, Config::default(), 4, 100_000).unwrap();
            assert_eq!(
                (rec.score, rec.steps, rec.lost),
                (summary.score, summary.steps, summary.lost)
            );
            let t = rec.steps as usize;
            assert_eq!(rec.observations.len(), (t + 1) * OBSERVATION_SIZE);
            assert_eq!(rec.action_masks.len(), (t + 1) * NUM_ACTIONS);
            assert_eq!(rec.rewards.len(), 4 * t);
            assert!(rec.terminated);
        }
    }

    #[test]
    fn a_set_stop_flag_abandons_the_episode() {
        let stop = AtomicBool::new(true);
        let rec = record_until(PolicyKind::Expert, Config::default(), 0, 100, false, &stop);
        assert_eq!(rec, Ok(None));
    }

    #[test]
    fn plans_check_seeds_steps_and_config() {
        let plan = |seeds: Vec<u64>, max_steps| {
            RolloutPlan::new(
                PolicyKind::Expert,
                seeds,
                max_steps,
                Config::default(),
                false,
            )
        };
        let ok = plan(vec![1, 2], None).unwrap();
        assert_eq!(ok.max_steps, MAX_ROLLOUT_STEPS);
        assert_eq!(
            ok.bytes(),
            3 * (u64::from(MAX_ROLLOUT_STEPS) + 1) * MAX_BYTES_PER_STEP
        );
        let refused = |r: Result<RolloutPlan, RolloutError>| match r {
            Err(RolloutError::InvalidArgument(m)) => m,
            other => panic!("not refused: {other:?}"),
        };
        assert!(refused(plan(vec![], None)).starts_with("seeds must hold"));
        let too_many = vec![0; MAX_ROLLOUT_EPISODES as usize + 1];
        assert!(refused(plan(too_many, None)).starts_with("seeds must hold"));
        assert!(refused(plan(vec![0], Some(0))).starts_with("max_steps must be in"));
        let bad = Config {
            lives: 0,
            ..Config::default()
        };
        assert!(
            RolloutPlan::new(PolicyKind::Random, vec![0], None, bad, false).is_err(),
            "an invalid configuration is refused"
        );
    }

    #[test]
    fn an_episode_played_in_chunks_is_the_episode_played_at_once() {
        let never = AtomicBool::new(false);
        for policy in [PolicyKind::Expert, PolicyKind::Random, PolicyKind::Planner] {
            let whole = record(policy, Config::default(), 9, 300, true).unwrap();
            let mut recorder = Recorder::new(policy, Config::default(), 9, 300, true).unwrap();
            // A deadline already passed: one step a chunk.
            let mut chunks = 0;
            while recorder.play(Some(Instant::now()), &never) == Played::Paused {
                chunks += 1;
            }
            assert_eq!(chunks + 1, whole.steps, "{policy:?}");
            assert_eq!(recorder.finish(), whole, "{policy:?}");
        }
    }

    #[test]
    fn max_steps_truncates() {
        let rec = record(PolicyKind::Expert, Config::default(), 0, 5, false).unwrap();
        assert_eq!(rec.steps, 5);
        assert!(rec.truncated && !rec.terminated);
        assert!(rec.action_masks.is_empty());
    }
}
