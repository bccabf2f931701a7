//! Random streams. Every realization's stream is a pure function of (master seed, index), so
//! results do not depend on thread count, shard layout or resume history:
//!
//! `stream(master, index)` = Xoshiro256++ whose 256-bit state is four consecutive SplitMix64
//! outputs started from `master XOR (index * 0x9E3779B97F4A7C15)` after one SplitMix64 round of
//! `master` (so that neighbouring masters and indices give unrelated states).

use rand::SeedableRng;
use rand_xoshiro::Xoshiro256PlusPlus;

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The random stream of realization `index` of a campaign with seed `master`.
pub fn stream(master: u64, index: u64) -> Xoshiro256PlusPlus {
    let mut s = master;
    let mixed = splitmix64(&mut s) ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    let mut st = mixed;
    let mut seed = [0u8; 32];
    for chunk in seed.chunks_mut(8) {
        chunk.copy_from_slice(&splitmix64(&mut st).to_le_bytes());
    }
    Xoshiro256PlusPlus::from_seed(seed)
}
