//! Policies that read the game: the benchmark's reference heuristic expert (docs/rules.md §8) and
//! a uniformly random policy. Further experts (deeper look-ahead) implement [`Policy`] beside them.

use rand::{Rng, SeedableRng, rngs::SmallRng};

use crate::sim::{NUM_ACTIONS, Restaurant};

/// Something that picks an action in a state.
pub trait Policy {
    /// The action to take in `restaurant`.
    fn act(&mut self, restaurant: &Restaurant) -> u8;
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
    fn act(&mut self, restaurant: &Restaurant) -> u8 {
        expert_action(restaurant)
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
    fn act(&mut self, _restaurant: &Restaurant) -> u8 {
        self.rng.random_range(0..NUM_ACTIONS as u8)
    }
}
