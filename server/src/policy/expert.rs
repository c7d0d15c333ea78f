//! The benchmark's reference heuristic expert (docs/rules.md §8): one-step greedy on the shaped
//! score.

use super::Policy;
use crate::sim::{Game, NUM_ACTIONS, Restaurant};

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
