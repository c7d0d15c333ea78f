#![allow(missing_docs)] // criterion_group! generates undocumented items.

//! Simulator, expert and planner speed: one random step, one expert decision, a whole expert
//! episode, the benchmark's 274 expert episodes end to end, and planner decisions (the mean over
//! an episode and the state with the most legal actions). Each bench also checks its result.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use dinerdash_server::cmd::eval::evaluate;
use dinerdash_server::policy::{Planner, PolicyKind, expert_action, run_episode};
use dinerdash_server::sim::{Config, Game, NUM_ACTIONS, Restaurant};
use rand::{Rng, SeedableRng, rngs::SmallRng};

fn reset(seed: u64) -> Restaurant {
    let mut game = Game::new(Config::default()).expect("v0 is valid");
    game.reset(Some(seed), None).expect("drawn arrivals");
    *game.restaurant()
}

/// States an expert episode passes through.
fn expert_states(seed: u64) -> Vec<Restaurant> {
    let mut r = reset(seed);
    let mut states = vec![r];
    while !r.is_terminated() {
        r.step(expert_action(&r));
        states.push(r);
    }
    states
}

fn step(c: &mut Criterion) {
    let start = reset(0);
    let mut rng = SmallRng::seed_from_u64(1);
    let actions: Vec<u8> = (0..4096)
        .map(|_| rng.random_range(0..NUM_ACTIONS as u8))
        .collect();
    let mut group = c.benchmark_group("step");
    group.throughput(Throughput::Elements(actions.len() as u64));
    group.bench_function("random_actions_x4096", |b| {
        let mut r = start;
        b.iter(|| {
            for &a in &actions {
                if r.step(black_box(a)).terminated {
                    r = start;
                }
            }
            black_box(r.score())
        })
    });
    group.finish();
}

fn expert(c: &mut Criterion) {
    let states = expert_states(0);
    assert_eq!(
        states.len(),
        1 + run_episode(PolicyKind::Expert, Config::default(), 0, u32::MAX)
            .unwrap()
            .steps as usize
    );
    let mut group = c.benchmark_group("expert");
    group.throughput(Throughput::Elements(states.len() as u64));
    group.bench_function("decision_over_one_episode_of_states", |b| {
        b.iter(|| {
            let mut sum = 0u32;
            for s in &states {
                sum += u32::from(expert_action(black_box(s)));
            }
            sum
        })
    });
    group.bench_function("episode_seed_0", |b| {
        b.iter(|| {
            let e = run_episode(
                PolicyKind::Expert,
                Config::default(),
                black_box(0),
                u32::MAX,
            )
            .unwrap();
            assert!(e.terminated);
            e.score
        })
    });
    group.sample_size(10);
    group.bench_function("274_episodes_one_thread", |b| {
        b.iter(|| {
            let e = evaluate(PolicyKind::Expert, Config::default(), 0, 274, u32::MAX, 1).unwrap();
            assert_eq!(e.episodes.len(), 274);
            e.total_steps()
        })
    });
    group.bench_function("274_episodes_all_cores", |b| {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        b.iter(|| {
            let e = evaluate(
                PolicyKind::Expert,
                Config::default(),
                0,
                274,
                u32::MAX,
                threads,
            )
            .unwrap();
            assert_eq!(e.episodes.len(), 274);
            e.total_steps()
        })
    });
    group.finish();
}

/// The games a planner episode passes through (capped: planner episodes are long).
fn planner_states(seed: u64, cap: usize) -> Vec<Game> {
    let planner = Planner::default();
    let mut game = Game::new(Config::default()).expect("v0 is valid");
    game.reset(Some(seed), None).expect("drawn arrivals");
    let mut states = vec![game.clone()];
    while !game.restaurant().is_terminated() && states.len() < cap {
        let action = planner.choose(&game);
        game.step(i64::from(action)).expect("a legal action");
        states.push(game.clone());
    }
    states
}

fn planner(c: &mut Criterion) {
    let states = planner_states(0, 2000);
    assert!(states.len() > 100, "a whole planner episode");
    let planner = Planner::default();
    let legal = |g: &Game| g.restaurant().action_mask().iter().filter(|&&m| m).count();
    let busiest = states
        .iter()
        .max_by_key(|g| legal(g))
        .expect("states")
        .clone();
    let mut group = c.benchmark_group("planner");
    group.sample_size(10);
    group.throughput(Throughput::Elements(states.len() as u64));
    group.bench_function("decision_over_one_episode_of_states", |b| {
        b.iter(|| {
            let mut sum = 0u32;
            for g in &states {
                let action = planner.choose(black_box(g));
                assert!(g.restaurant().action_mask()[usize::from(action)]);
                sum += u32::from(action);
            }
            sum
        })
    });
    group.throughput(Throughput::Elements(1));
    group.bench_function("decision_with_the_most_legal_actions", |b| {
        b.iter(|| planner.choose(black_box(&busiest)))
    });
    group.finish();
}

fn reset_and_snapshot(c: &mut Criterion) {
    let mut game = Game::new(Config::default()).unwrap();
    game.reset(Some(0), None).unwrap();
    let mut group = c.benchmark_group("game");
    group.bench_function("reset_drawing_200_groups", |b| {
        b.iter(|| game.reset(None, None).unwrap())
    });
    group.bench_function("clone_restaurant", |b| {
        b.iter(|| *black_box(game.restaurant()))
    });
    group.bench_function("snapshot_restore", |b| {
        b.iter(|| Game::restore(&game.snapshot()).unwrap())
    });
    group.finish();
}

criterion_group!(benches, step, expert, planner, reset_and_snapshot);
criterion_main!(benches);
