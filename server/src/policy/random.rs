//! Uniformly random actions: the benchmark's random baseline.

use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::Policy;
use crate::sim::{Game, NUM_ACTIONS};

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
