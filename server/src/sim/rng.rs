//! The arrival generator: MT19937 seeded and sampled exactly like CPython's `random` module
//! (docs/rules.md §2), so that `reset(seed=s)` draws the reference's customers.

use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

const N: usize = 624;
const M: usize = 397;
const MATRIX_A: u32 = 0x9908_b0df;
const UPPER_MASK: u32 = 0x8000_0000;
const LOWER_MASK: u32 = 0x7fff_ffff;

/// 32-bit Mersenne Twister with CPython's seeding (`init_by_array` over the seed's 32-bit words).
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Mt19937 {
    /// The 624-word state vector.
    #[serde(with = "BigArray")]
    state: [u32; N],
    /// Next word of `state` to temper; `N` means the vector must be regenerated first.
    index: usize,
}

impl std::fmt::Debug for Mt19937 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mt19937")
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl Mt19937 {
    /// The generator after CPython's `random.seed(seed)` for a non-negative integer seed.
    pub fn from_seed(seed: u64) -> Self {
        let low = seed as u32;
        let high = (seed >> 32) as u32;
        if high == 0 {
            Self::from_key(&[low])
        } else {
            Self::from_key(&[low, high])
        }
    }

    fn from_init(seed: u32) -> Self {
        let mut state = [0u32; N];
        state[0] = seed;
        for i in 1..N {
            state[i] = 1_812_433_253u32
                .wrapping_mul(state[i - 1] ^ (state[i - 1] >> 30))
                .wrapping_add(i as u32);
        }
        Mt19937 { state, index: N }
    }

    /// MT19937's `init_by_array`.
    fn from_key(key: &[u32]) -> Self {
        let mut mt = Self::from_init(19_650_218);
        let s = &mut mt.state;
        let (mut i, mut j) = (1usize, 0usize);
        for _ in 0..N.max(key.len()) {
            s[i] = (s[i] ^ (s[i - 1] ^ (s[i - 1] >> 30)).wrapping_mul(1_664_525))
                .wrapping_add(key[j])
                .wrapping_add(j as u32);
            i += 1;
            j += 1;
            if i >= N {
                s[0] = s[N - 1];
                i = 1;
            }
            if j >= key.len() {
                j = 0;
            }
        }
        for _ in 0..N - 1 {
            s[i] = (s[i] ^ (s[i - 1] ^ (s[i - 1] >> 30)).wrapping_mul(1_566_083_941))
                .wrapping_sub(i as u32);
            i += 1;
            if i >= N {
                s[0] = s[N - 1];
                i = 1;
            }
        }
        s[0] = 0x8000_0000;
        mt
    }

    fn regenerate(&mut self) {
        // The reference's three loops: no index wraps inside a loop, so no `% N` per word (a
        // reset draws ~470 words: this ran once per reset and a half).
        let twist = |this: u32, next: u32, far: u32| {
            let y = (this & UPPER_MASK) | (next & LOWER_MASK);
            far ^ (y >> 1) ^ (y & 1).wrapping_neg() & MATRIX_A
        };
        let s = &mut self.state;
        for k in 0..N - M {
            s[k] = twist(s[k], s[k + 1], s[k + M]);
        }
        for k in N - M..N - 1 {
            s[k] = twist(s[k], s[k + 1], s[k + M - N]);
        }
        s[N - 1] = twist(s[N - 1], s[0], s[M - 1]);
        self.index = 0;
    }

    /// The next 32-bit output (`genrand_uint32`).
    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        if self.index >= N {
            self.regenerate();
        }
        let mut y = self.state[self.index];
        self.index += 1;
        y ^= y >> 11;
        y ^= (y << 7) & 0x9d2c_5680;
        y ^= (y << 15) & 0xefc6_0000;
        y ^= y >> 18;
        y
    }

    /// CPython's `randint(lo, hi)` for a small range: rejection sampling on the top `k` bits,
    /// where `k` is the bit length of the range's size.
    pub fn uniform(&mut self, lo: u32, hi: u32) -> u32 {
        let n = hi - lo + 1;
        let k = 32 - n.leading_zeros();
        loop {
            let r = self.next_u32() >> (32 - k);
            if r < n {
                return lo + r;
            }
        }
    }

    /// CPython's `randint(lo, hi)` for each of two small ranges in turn, into every pair of
    /// `out`: exactly the numbers of alternating [`Self::uniform`] calls. Without a branch per
    /// draw: every draw is written to the slot it would fill and the slot moves on only when the
    /// draw is accepted, since which draws are rejected is random and a branch on it mispredicts
    /// (a reset's 200 arrivals reject ~270 of ~670 draws).
    pub fn uniform_pairs(&mut self, ranges: [(u32, u32); 2], out: &mut [[u32; 2]]) {
        let size = ranges.map(|(lo, hi)| hi - lo + 1);
        // `uniform` keeps the top k = 32 - leading_zeros bits: a shift by the leading zeros.
        let shift = size.map(u32::leading_zeros);
        let total = 2 * out.len();
        let mut slot = 0;
        while slot < total {
            let which = slot & 1;
            let r = self.next_u32() >> shift[which];
            out[slot / 2][which] = ranges[which].0 + r;
            slot += usize::from(r < size[which]);
        }
    }

    /// Whether the state could have come from this generator (used when restoring snapshots).
    pub(crate) fn is_consistent(&self) -> bool {
        self.index <= N
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `random.seed(S); [random.getrandbits(32) for _ in range(3)]` in CPython 3.11.
    #[test]
    fn matches_cpython_getrandbits() {
        let cases: [(u64, [u32; 3]); 3] = [
            (0, [3_626_764_237, 1_654_615_998, 3_255_389_356]),
            (42, [2_746_317_213, 478_163_327, 107_420_369]),
            (4_294_967_296, [485_306_839, 1_508_871_100, 1_794_561_286]),
        ];
        for (seed, want) in cases {
            let mut mt = Mt19937::from_seed(seed);
            let got = [mt.next_u32(), mt.next_u32(), mt.next_u32()];
            assert_eq!(got, want, "seed {seed}");
        }
    }

    /// `random.seed(7); [random.randint(1, 6) for _ in range(10)]` in CPython 3.11.
    #[test]
    fn matches_cpython_randint() {
        let mut mt = Mt19937::from_seed(7);
        let got: Vec<u32> = (0..10).map(|_| mt.uniform(1, 6)).collect();
        assert_eq!(got, vec![3, 2, 4, 6, 1, 1, 5, 1, 3, 5]);
    }

    #[test]
    fn uniform_pairs_are_alternating_uniform_draws() {
        for seed in [0, 7, 42, 1 << 40] {
            let ranges = [(1, 2), (1, 6)];
            let mut one = Mt19937::from_seed(seed);
            let mut pairs = Mt19937::from_seed(seed);
            // Long enough to cross several regenerations of the state.
            let want: Vec<[u32; 2]> = (0..1000)
                .map(|_| [one.uniform(1, 2), one.uniform(1, 6)])
                .collect();
            let mut got = vec![[0; 2]; 1000];
            pairs.uniform_pairs(ranges, &mut got);
            assert_eq!(got, want, "seed {seed}");
            assert_eq!(
                pairs.next_u32(),
                one.next_u32(),
                "seed {seed}: same stream after"
            );
        }
    }
}
