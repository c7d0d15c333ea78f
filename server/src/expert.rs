//! Policies that read the game: the benchmark's reference heuristic expert (docs/rules.md §8), a
//! uniformly random policy, and [`PolicyKind`], the names by which the command line, Rollout and
//! sessions choose among them and the look-ahead planner ([`crate::planner`]).

use rand::{Rng, SeedableRng, rngs::SmallRng};

use crate::planner::Planner;
use crate::sim::{Game, NUM_ACTIONS, Restaurant};

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

/// The reference expert: one-step greedy on the shaped score, first best action, 0 unless the
/// best change is strictly positive.
#[derive(Debug, Clone, Copy, Default)]
pub struct Expert;

/// The reference expert's choice in `restaurant`.
pub fn expert_action(restaurant: &Restaurant) -> u8 {
    // An action whose preconditions fail only lets time pass, exactly like action 0, which comes
    // first: skipping illegal actions cannot change the (first) best choice.
    let mut best_action = 0u8;
    let mut best_gain = restaurant.shaped_step_gain(0);
    let mask = restaurant.action_mask();
    for a in 1..NUM_ACTIONS as u8 {
        if mask[usize::from(a)] {
            let gain = restaurant.shaped_step_gain(a);
            if gain > best_gain {
                best_gain = gain;
                best_action = a;
            }
        }
    }
    if best_gain > 0 { best_action } else { 0 }
}

impl Policy for Expert {
    fn act(&mut self, game: &Game) -> u8 {
        expert_action(game.restaurant())
    }
}

/// Uniformly random actions in 0..=56, from a seeded generator (the benchmark's random baseline).
#[derive(Debug, Clone)]
pub struct RandomPolicy {
    /// Source of the actions.
    rng: SmallRng,
}

impl RandomPolicy {
    /// A random policy whose choices are fixed by `seed`.
    pub fn new(seed: u64) -> Self {
        RandomPolicy {
            rng: SmallRng::seed_from_u64(seed),
        }
    }
}

impl Policy for RandomPolicy {
    fn act(&mut self, _game: &Game) -> u8 {
        self.rng.random_range(0..NUM_ACTIONS as u8)
    }
}
