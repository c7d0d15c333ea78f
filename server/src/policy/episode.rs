//! One episode of a policy from a seed, summarised: what the `eval` command runs many of, and
//! what the tests compare Rollout's and the sessions' episodes with.

use super::PolicyKind;
use crate::sim::{Config, Game};

/// How one episode ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EpisodeSummary {
    /// The reset seed.
    pub seed: u64,
    /// Final score.
    pub score: i64,
    /// Steps taken.
    pub steps: u32,
    /// Groups lost.
    pub lost: u32,
    /// Ended by losing groups (rather than the step cap or time limit).
    pub terminated: bool,
}

/// Plays one episode from `reset(seed)` until it terminates, is truncated, or `max_steps` pass.
pub fn run_episode(
    kind: PolicyKind,
    config: Config,
    seed: u64,
    max_steps: u32,
) -> Result<EpisodeSummary, crate::sim::ConfigError> {
    let mut game = Game::new(config)?;
    // A drawn arrival list never fails.
    let _ = game.reset(Some(seed), None);
    let mut policy = kind.build(seed);
    let mut steps = 0;
    let mut terminated = false;
    while steps < max_steps {
        let action = policy.act(&game);
        let Ok(outcome) = game.step(i64::from(action)) else {
            break;
        };
        steps += 1;
        if outcome.terminated || outcome.truncated {
            terminated = outcome.terminated;
            break;
        }
    }
    let r = game.restaurant();
    Ok(EpisodeSummary {
        seed,
        score: r.score(),
        steps,
        lost: r.lost(),
        terminated,
    })
}
