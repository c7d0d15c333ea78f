//! A step, an expert decision and a planner decision allocate nothing: counted with a wrapping
//! global allocator.
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use dinerdash_server::policy::{Planner, expert_action};
use dinerdash_server::sim::{Config, Game, NUM_ACTIONS};

struct Counting;

thread_local! {
    /// Allocations made by this thread: the test harness runs tests (and its own bookkeeping) on
    /// other threads at the same time, and their allocations are not the code under test's.
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

/// Allocations made so far by the calling thread.
fn allocations() -> usize {
    ALLOCATIONS.with(Cell::get)
}

// SAFETY: forwards to the system allocator unchanged, only counting calls.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // `try_with`: a thread being torn down may still allocate.
        let _ = ALLOCATIONS.try_with(|n| n.set(n.get() + 1));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

#[test]
fn steps_and_expert_decisions_do_not_allocate() {
    let mut game = Game::new(Config::default()).unwrap();
    game.reset(Some(3), None).unwrap();
    let before = allocations();
    let mut steps = 0u32;
    for i in 0..20_000u32 {
        let r = game.restaurant();
        let action = if i % 3 == 0 {
            (i * 7) % NUM_ACTIONS as u32
        } else {
            u32::from(expert_action(r))
        };
        let _ = std::hint::black_box(r.observation());
        let _ = std::hint::black_box(r.action_mask());
        if game.step(i64::from(action)).unwrap().terminated {
            break;
        }
        steps += 1;
    }
    let after = allocations();
    assert!(steps > 100);
    assert_eq!(
        after - before,
        0,
        "{} allocations in {steps} steps",
        after - before
    );
}

#[test]
fn planner_decisions_do_not_allocate() {
    // The counter sees this thread's allocations.
    let n = allocations();
    drop(std::hint::black_box(vec![1u8; 16]));
    assert_eq!(allocations(), n + 1);
    let planner = Planner::default();
    let mut game = Game::new(Config::default()).unwrap();
    game.reset(Some(4), None).unwrap();
    let before = allocations();
    let mut decisions = 0u32;
    for _ in 0..300 {
        let action = planner.choose(&game);
        decisions += 1;
        if game.step(i64::from(action)).unwrap().terminated {
            break;
        }
    }
    let after = allocations();
    assert_eq!(
        after - before,
        0,
        "{} allocations in {decisions} planner decisions",
        after - before
    );
}
