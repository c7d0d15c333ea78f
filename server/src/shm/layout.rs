//! The region's layout: a header, then every array of a Step at a fixed offset and its full
//! capacity for N environments, so that a client maps each one once as a numpy array and builds
//! no object per environment (version 2; docs/shm.md describes it for other clients).
//!
//! ```text
//! offset 0    u32 MAGIC, u32 VERSION, u32 N, u32 FIELDS, u64 region bytes
//! offset 32   FIELDS x (u32 offset, u32 capacity)   where each array lives
//! offset 256  FIELDS x u32 length                    bytes the last reply wrote to each array
//!             then u32 drain_remaining_ms            as the Batch's field (0: not draining)
//! offset 512  the arrays, each at a 64-byte boundary, in the order of [`FIELDS`]
//! ```
//!
//! All integers are little-endian. The client writes only `actions` (N x int32); the server
//! reads only `actions` and writes everything else.

use crate::session::Batch;
use crate::sim::{NUM_ACTIONS, OBSERVATION_SIZE};

/// "DDsh" as a little-endian u32.
pub const MAGIC: u32 = u32::from_le_bytes(*b"DDsh");
/// This layout's version.
pub const VERSION: u32 = 2;
/// Where the offset table starts.
const TABLE: usize = 32;
/// Where the length table starts.
const LENGTHS: usize = 256;
/// Where the last reply's `drain_remaining_ms` lies: right after the length table, so that one
/// write carries both.
pub const DRAIN_AT: usize = LENGTHS + 4 * FIELDS.len();
/// Where the first array starts.
const ARRAYS: usize = 512;
/// Arrays start at this alignment (a cache line).
const ALIGN: usize = 64;

/// The arrays of the region, in order, with their bytes per environment: `actions` first (the
/// only one the client writes), then the fields of `dinerdash.v1.Batch` by their proto names.
pub const FIELDS: [(&str, usize); 19] = [
    ("actions", 4),
    ("observations", OBSERVATION_SIZE),
    ("rewards", 4),
    ("terminated", 1),
    ("truncated", 1),
    ("scores", 4),
    ("lost", 4),
    ("ticks", 4),
    ("action_masks", NUM_ACTIONS),
    ("expert_actions", 1),
    ("reset", 1),
    ("seeds", 8),
    ("stream_episodes", 4),
    ("final_observations", OBSERVATION_SIZE),
    ("final_scores", 4),
    ("final_lost", 4),
    ("final_ticks", 4),
    ("final_action_masks", NUM_ACTIONS),
    ("final_expert_actions", 1),
];

/// Where each array of a region for N environments lives.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    /// N.
    pub num_envs: usize,
    /// `(offset, capacity)` of each array of [`FIELDS`].
    pub arrays: Vec<(usize, usize)>,
    /// The region's size, whole pages.
    pub bytes: usize,
}

impl Layout {
    /// The layout for `num_envs` environments.
    pub fn new(num_envs: usize) -> Layout {
        let mut at = ARRAYS;
        let arrays = FIELDS
            .iter()
            .map(|&(_, width)| {
                let here = at;
                at = (at + width * num_envs).next_multiple_of(ALIGN);
                (here, width * num_envs)
            })
            .collect();
        Layout {
            num_envs,
            arrays,
            bytes: at.next_multiple_of(4096),
        }
    }

    /// The header: magic, version, N, the offset table (lengths all zero).
    pub fn header(&self) -> Vec<u8> {
        let mut h = vec![0u8; ARRAYS];
        let mut put = |at: usize, v: u32| h[at..at + 4].copy_from_slice(&v.to_le_bytes());
        put(0, MAGIC);
        put(4, VERSION);
        put(8, self.num_envs as u32);
        put(12, FIELDS.len() as u32);
        for (i, &(offset, capacity)) in self.arrays.iter().enumerate() {
            put(TABLE + 8 * i, offset as u32);
            put(TABLE + 8 * i + 4, capacity as u32);
        }
        h[16..24].copy_from_slice(&(self.bytes as u64).to_le_bytes());
        h
    }

    /// Where `actions` lives: `(offset, bytes)`.
    pub fn actions(&self) -> (usize, usize) {
        self.arrays[0]
    }

    /// Where the length of array `i` is written.
    pub fn length_at(i: usize) -> usize {
        LENGTHS + 4 * i
    }
}

/// Each array of `batch` after `actions`, in [`FIELDS`] order, as little-endian bytes (`seeds`
/// and `stream_episodes` are the only ones not bytes already).
pub fn batch_arrays<'a>(batch: &'a Batch, scratch: &'a mut Vec<u8>) -> [&'a [u8]; 18] {
    // The two integer arrays are encoded into `scratch`: seeds first, then stream_episodes.
    scratch.clear();
    for s in &batch.seeds {
        scratch.extend_from_slice(&s.to_le_bytes());
    }
    let seeds_end = scratch.len();
    for e in &batch.stream_episodes {
        scratch.extend_from_slice(&e.to_le_bytes());
    }
    let (seeds, episodes) = scratch.split_at(seeds_end);
    [
        &batch.observations,
        &batch.rewards,
        &batch.terminated,
        &batch.truncated,
        &batch.scores,
        &batch.lost,
        &batch.ticks,
        &batch.action_masks,
        &batch.expert_actions,
        &batch.reset,
        seeds,
        episodes,
        &batch.final_observations,
        &batch.final_scores,
        &batch.final_lost,
        &batch.final_ticks,
        &batch.final_action_masks,
        &batch.final_expert_actions,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_are_aligned_disjoint_and_inside_the_region() {
        for n in [1, 7, 256, 1024] {
            let l = Layout::new(n);
            let mut end = ARRAYS;
            for (&(offset, capacity), &(_, width)) in l.arrays.iter().zip(&FIELDS) {
                assert_eq!(offset % ALIGN, 0);
                assert!(offset >= end);
                assert_eq!(capacity, width * n);
                end = offset + capacity;
            }
            assert!(end <= l.bytes);
            assert_eq!(l.bytes % 4096, 0);
            let h = l.header();
            assert_eq!(&h[..4], b"DDsh");
            assert_eq!(u32::from_le_bytes(h[8..12].try_into().unwrap()), n as u32);
        }
    }
}
