//! The trajectories recorded from the reference simulator (`tests/data/conformance/*.jsonl`, or
//! `DINERDASH_CONFORMANCE_DIR`), read at run time; shared by the tests that replay them.

#![allow(dead_code)]

use std::path::PathBuf;

use serde::Deserialize;

/// One recorded episode (one line of a `.jsonl` file).
#[derive(Deserialize)]
pub struct Episode {
    pub seed: u64,
    pub reset_obs: Vec<i64>,
    pub steps: Vec<Step>,
}

/// One recorded step: the action taken, the expert's choice before it, and the result.
#[derive(Deserialize)]
pub struct Step {
    pub action: i64,
    pub expert_action: i64,
    pub obs: Vec<i64>,
    pub reward: i64,
    pub terminated: bool,
    pub score: i64,
    pub lost: u32,
}

/// Every recorded episode, with `file:line (seed S)` to name it in failures. Panics loudly when
/// the data is missing: a replay of nothing proves nothing.
pub fn episodes() -> Vec<(String, Episode)> {
    let dir = std::env::var_os("DINERDASH_CONFORMANCE_DIR").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/conformance"),
        PathBuf::from,
    );
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
    let mut episodes = Vec::new();
    for path in files {
        let text = std::fs::read_to_string(&path).unwrap();
        for (line_no, line) in text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
        {
            let episode: Episode = serde_json::from_str(line)
                .unwrap_or_else(|e| panic!("{}:{}: {e}", path.display(), line_no + 1));
            let at = format!("{}:{} (seed {})", path.display(), line_no + 1, episode.seed);
            episodes.push((at, episode));
        }
    }
    episodes
}
