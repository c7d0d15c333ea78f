//! Policies that read the game, and [`PolicyKind`], the names by which the command line, Rollout
//! and sessions choose among them.
//!
//! - [`expert`]: the benchmark's reference heuristic expert (docs/rules.md §8).
//! - [`random`]: uniformly random actions, the benchmark's random baseline.
//! - [`planner`]: the look-ahead planner over sampled futures, which never reads what arrives
//!   next.
//! - [`episode`]: one episode of a policy from a seed ([`run_episode`]), summarised.

pub mod episode;
pub mod expert;
pub mod planner;
pub mod random;

pub use episode::{EpisodeSummary, run_episode};
pub use expert::{Expert, expert_action};
pub use planner::Planner;
pub use random::RandomPolicy;

use crate::sim::Game;

/// Something that picks an action in a game's current state.
pub trait Policy {
    /// The action to take in `game`'s current episode. A policy may read what a player sees and
    /// the seed that names the episode, never the episode's arrival list.
    fn act(&mut self, game: &Game) -> u8;
}

/// The policies the command line, the Rollout RPC and sessions know.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PolicyKind {
    /// The reference heuristic expert.
    Expert,
    /// Uniformly random actions.
    Random,
    /// The look-ahead planner over sampled futures.
    Planner,
}

impl PolicyKind {
    /// A fresh policy for the episode of `seed` (the random policy is seeded from it, so an
    /// evaluation is reproducible; the planner seeds itself from the game it plays).
    pub fn build(self, seed: u64) -> Box<dyn Policy + Send> {
        match self {
            PolicyKind::Expert => Box::new(Expert),
            PolicyKind::Random => Box::new(RandomPolicy::new(seed ^ 0x9e37_79b9_7f4a_7c15)),
            PolicyKind::Planner => Box::new(Planner::default()),
        }
    }
}
