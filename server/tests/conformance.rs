//! Replays every trajectory recorded from the reference simulator (`tests/data/conformance`) and
//! checks every number of every step, and the expert's choice before each step.

use dinerdash_server::policy::expert_action;
use dinerdash_server::sim::{Config, Game};

mod recorded;

fn obs_i64(game: &Game) -> Vec<i64> {
    game.restaurant()
        .observation()
        .iter()
        .map(|&v| i64::from(v))
        .collect()
}

#[test]
fn every_recorded_trajectory_replays_exactly() {
    let mut episodes = 0;
    let mut steps = 0;
    for (at, ep) in recorded::episodes() {
        let mut game = Game::new(Config::default()).unwrap();
        game.reset(Some(ep.seed), None).unwrap();
        assert_eq!(obs_i64(&game), ep.reset_obs, "{at}: reset observation");
        for (i, s) in ep.steps.iter().enumerate() {
            let want_expert = i64::from(expert_action(game.restaurant()));
            assert_eq!(want_expert, s.expert_action, "{at} step {i}: expert action");
            let out = game.step(s.action).unwrap();
            let after = format!("{at} step {i}, action {}", s.action);
            assert_eq!(obs_i64(&game), s.obs, "{after}: observation");
            assert_eq!(out.reward, s.reward, "{after}: reward");
            assert_eq!(out.terminated, s.terminated, "{after}: terminated");
            assert_eq!(game.restaurant().score(), s.score, "{after}: score");
            assert_eq!(game.restaurant().lost(), s.lost, "{after}: lost");
            steps += 1;
        }
        episodes += 1;
    }
    assert!(episodes > 0);
    println!("replayed {episodes} episodes, {steps} steps");
}
