//! Replays every trajectory recorded from the reference simulator (`../shared/conformance`) and
//! checks every number of every step, and the expert's choice before each step.

use std::path::PathBuf;

use dinerdash_server::expert::expert_action;
use dinerdash_server::sim::{Config, Game};
use serde::Deserialize;

#[derive(Deserialize)]
struct Episode {
    seed: u64,
    reset_obs: Vec<i64>,
    steps: Vec<Step>,
}

#[derive(Deserialize)]
struct Step {
    action: i64,
    expert_action: i64,
    obs: Vec<i64>,
    reward: i64,
    terminated: bool,
    score: i64,
    lost: u32,
}

/// `../shared/conformance` beside the workspace, or `DINERDASH_CONFORMANCE_DIR`.
fn conformance_dir() -> PathBuf {
    std::env::var_os("DINERDASH_CONFORMANCE_DIR").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/conformance"),
        PathBuf::from,
    )
}

fn files() -> Vec<PathBuf> {
    let dir = conformance_dir();
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("conformance data not found at {}: {e}", dir.display()))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "jsonl"))
        .collect();
    files.sort();
    assert!(
        !files.is_empty(),
        "no *.jsonl trajectories in {}",
        dir.display()
    );
    files
}

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
    for path in files() {
        let text = std::fs::read_to_string(&path).unwrap();
        for (line_no, line) in text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
        {
            let ep: Episode = serde_json::from_str(line).unwrap();
            let at = format!("{}:{} (seed {})", path.display(), line_no + 1, ep.seed);
            let mut game = Game::new(Config::default()).unwrap();
            game.reset(Some(ep.seed), None).unwrap();
            assert_eq!(obs_i64(&game), ep.reset_obs, "{at}: reset observation");
            for (i, s) in ep.steps.iter().enumerate() {
                let want_expert = i64::from(expert_action(game.restaurant()));
                assert_eq!(want_expert, s.expert_action, "{at} step {i}: expert action");
                let out = game.step(s.action).unwrap();
                assert_eq!(
                    obs_i64(&game),
                    s.obs,
                    "{at} step {i}: observation after action {}",
                    s.action
                );
                assert_eq!(out.reward, s.reward, "{at} step {i}: reward");
                assert_eq!(out.terminated, s.terminated, "{at} step {i}: terminated");
                assert_eq!(game.restaurant().score(), s.score, "{at} step {i}: score");
                assert_eq!(game.restaurant().lost(), s.lost, "{at} step {i}: lost");
                steps += 1;
            }
            episodes += 1;
        }
    }
    assert!(episodes > 0);
    println!("replayed {episodes} episodes, {steps} steps");
}
