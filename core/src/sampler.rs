//! Deterministic sample streams: Owen-scrambled Sobol (Burley 2020, `sobol_burley`).
//!
//! Sample `i` of pixel `(x, y)` depends only on the job seed, `(x, y)`, `i` and the dimension,
//! so any sample range of any pixel can be rendered anywhere, in any order. Dimensions come in
//! 4-D sets ("padding"): each set is a 4-D Sobol point set with its own scramble and shuffle
//! seed, hashed from the pixel seed and the set's index.
//!
//! Stratification pays off in the first dimensions (film, lens, the first bounces' light and
//! BSDF samples; which vertex takes which numbers: [`crate::integrator::path::li`]); an
//! Owen-scrambled set costs ~70 ns. Sets from [`SOBOL_SETS`] on (the choices at the third
//! vertex and everything after them) are therefore independent uniform numbers hashed from
//! the same coordinates: ~10 ns, equally deterministic.

use std::cell::Cell;

use sobol_burley::parts::{self, Int4};

use crate::math::{hash_step, hash_u32, hash_words, HASH_START};

/// 4-D sets drawn from Owen-scrambled Sobol; later sets are hashed uniform numbers.
pub const SOBOL_SETS: u32 = 6;

/// Sobol points per (scramble) sequence in `sobol_burley`.
const SEQUENCE_LEN: u32 = 1 << 16;

/// What every sample of one pixel shares, within one block of [`SEQUENCE_LEN`] sample indices:
/// the stream seed hashed from the job seed, the pixel and the block, and each Sobol set's
/// shuffle and scramble seeds hashed from it, each on its first use. Hashed once a pixel
/// instead of once a sample and set; the values are the same
/// (`pixel_seeds_give_the_per_sample_hashes`).
pub struct PixelSeeds {
    job_seed: u64,
    x: u32,
    y: u32,
    block: u32,
    seed: u32,
    /// [`hash_words`]' state after `seed`: the hashed sets' hashes start with it.
    after_seed: u32,
    sets: [Cell<Option<SetSeeds>>; SOBOL_SETS as usize],
}

/// A Sobol set's seeds: the index shuffle's and the four dimensions' Owen scrambles.
#[derive(Clone, Copy)]
struct SetSeeds {
    shuffle: u32,
    scramble: [u32; 4],
}

impl SetSeeds {
    /// `sobol_burley::sample_4d`'s seeds for `seed` (see [`sobol_set0`]).
    fn new(seed: u32) -> SetSeeds {
        let scramble = Int4::from([seed.wrapping_mul(0x9c8f_2d3b); 4])
            ^ Int4::from([0x912f_69ba, 0x174f_18ab, 0x691e_72ca, 0xb40c_c1b8]);
        SetSeeds { shuffle: parts::hash(seed ^ 0x79c6_8e4a), scramble: parts::hash_int4(scramble).into() }
    }
}

impl PixelSeeds {
    /// The seeds of pixel `(x, y)`'s samples under `job_seed`.
    pub fn new(job_seed: u64, x: u32, y: u32) -> PixelSeeds {
        let mut p = PixelSeeds { job_seed, x, y, block: 0, seed: 0, after_seed: 0, sets: Default::default() };
        p.set_block(0);
        p
    }

    fn set_block(&mut self, block: u32) {
        let j = self.job_seed;
        self.block = block;
        self.seed = hash_words(&[j as u32, (j >> 32) as u32, self.x, self.y, block]);
        self.after_seed = hash_step(HASH_START, self.seed);
        self.sets = Default::default();
    }

    /// Sobol set `set`'s seeds (below [`SOBOL_SETS`]), hashed on first use.
    #[inline]
    fn set(&self, set: usize) -> SetSeeds {
        let cell = &self.sets[set];
        match cell.get() {
            Some(s) => s,
            None => {
                let s = SetSeeds::new(hash_words(&[self.seed, set as u32]));
                cell.set(Some(s));
                s
            }
        }
    }

    /// Up to `N` streams at once, of samples `index..index + n` (one to `want`, within one
    /// block of [`SEQUENCE_LEN`]), and `n`; streams past `n` repeat the last.
    #[inline]
    pub fn streams<const N: usize>(&mut self, index: u64, want: usize) -> ([SampleStream<'_>; N], usize) {
        let block = (index / SEQUENCE_LEN as u64) as u32;
        if block != self.block {
            self.set_block(block);
        }
        let at = (index % SEQUENCE_LEN as u64) as u32;
        let n = want.min(N).min((SEQUENCE_LEN - at) as usize).max(1);
        let pixel = &*self;
        (std::array::from_fn(|j| SampleStream { pixel, index: at + j.min(n - 1) as u32, set: 0 }), n)
    }

    /// The stream of sample `index`. Sample indices past the sequence length continue in a
    /// fresh, independently scrambled sequence (the seeds are hashed again when the block
    /// changes).
    #[inline]
    pub fn stream(&mut self, index: u64) -> SampleStream<'_> {
        let ([s], _) = self.streams::<1>(index, 1);
        s
    }
}

/// The stream of one sample of one pixel.
pub struct SampleStream<'a> {
    pixel: &'a PixelSeeds,
    index: u32,
    set: u32,
}

impl SampleStream<'_> {
    /// The next 4 dimensions, as one stratified 4-D point in [0, 1)^4.
    #[inline]
    pub fn next_4d(&mut self) -> [f32; 4] {
        let set = self.set;
        self.set += 1;
        self.set_4d(set)
    }

    /// The next 4 dimensions without taking them: the values [`SampleStream::next_4d`] would
    /// give, which [`SampleStream::skip_4d`] then takes.
    #[inline]
    pub fn peek_4d(&self) -> [f32; 4] {
        self.set_4d(self.set)
    }

    /// The 4 dimensions `ahead` sets past the next, without taking any: what
    /// [`SampleStream::peek_4d`] will give after `ahead` sets are taken.
    #[inline]
    pub fn peek_4d_ahead(&self, ahead: u32) -> [f32; 4] {
        self.set_4d(self.set + ahead)
    }

    /// Takes the next 4 dimensions (read already by [`SampleStream::peek_4d`]).
    #[inline]
    pub fn skip_4d(&mut self) {
        self.set += 1;
    }

    /// Takes the next 4 dimensions without computing them: [`Deferred::get`] computes them if
    /// they are used. A set's values depend only on its coordinates, never on whether earlier
    /// sets were computed, so an unused set costs nothing and changes nothing.
    #[inline]
    pub fn defer_4d(&mut self) -> Deferred {
        self.set += 1;
        Deferred { set: self.set - 1, values: None }
    }

    // (Always inlined: as a call from the integrator's loop it cost cbox 1.1% more
    // instructions, once a change elsewhere in the loop tipped the inliner against it.)
    #[inline(always)]
    fn set_4d(&self, set: u32) -> [f32; 4] {
        if set < SOBOL_SETS {
            return sobol_point(self.index, &self.pixel.set(set as usize));
        }
        // hash_words(&[seed, set, index]), from the state after the seed.
        hashed_units(hash_step(hash_step(self.pixel.after_seed, set), self.index))
    }
}

/// A hashed set's four numbers from its hash `h`: each its own hash of `h`, 24 bits of it as
/// a float in [0, 1). With SSE4.1 where the CPU has it, the four at once (the same bits).
#[inline]
fn hashed_units(h: u32) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    if has_sse41() {
        // SAFETY: the CPU has SSE4.1.
        return unsafe { sse41::hashed_units(h) };
    }
    hashed_units_portable(h)
}

fn hashed_units_portable(h: u32) -> [f32; 4] {
    let unit = |k: u32| (hash_u32(h ^ k.wrapping_mul(0x9e37_79b9)) >> 8) as f32 * (1.0 / 16_777_216.0);
    [unit(1), unit(2), unit(3), unit(4)]
}

/// The first 4-D Sobol set of `sobol_burley` as two tables of 256 points: the (reversed) Sobol
/// matrix is linear over XOR, so the point of a 16-bit index is the XOR of its high byte's
/// point and its low byte's. 8 KiB, built once from the crate's own generator.
struct SobolTables {
    hi: [[u32; 4]; 256],
    lo: [[u32; 4]; 256],
}

static SOBOL_TABLES: std::sync::LazyLock<SobolTables> = std::sync::LazyLock::new(|| SobolTables {
    hi: std::array::from_fn(|h| parts::sobol_int4_rev((h as u32) << 24, 0).into()),
    lo: std::array::from_fn(|l| parts::sobol_int4_rev((l as u32) << 16, 0).into()),
});

/// `sobol_burley::sample_4d(index, 0, seed)`, bit for bit (`sobol_set0_is_sobol_burleys`), with
/// the per-bit loop over the index replaced by two table lookups. The same steps as the crate:
/// shuffle the index by a nested uniform scramble, take its Sobol point, Owen-scramble each
/// dimension, un-reverse and convert.
#[cfg(test)]
fn sobol_set0(index: u32, seed: u32) -> [f32; 4] {
    sobol_point(index, &SetSeeds::new(seed))
}

/// Whether this CPU runs the `sse41` module's functions (SSE4.1 and SSSE3; the detection is
/// cached, and compiled away where the build assumes them, as x86-64-v2 does).
#[cfg(target_arch = "x86_64")]
#[inline]
fn has_sse41() -> bool {
    std::is_x86_feature_detected!("sse4.1") && std::is_x86_feature_detected!("ssse3")
}

/// The instructions that compute Sobol sets on this CPU (the values are the same either way).
pub fn instruction_set() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    if has_sse41() {
        return "SSE4.1";
    }
    "portable"
}

/// [`sobol_set0`] with the seeds hashed already: with SSE4.1 where the CPU has it (the same
/// bits), the crate's portable 4-lane code otherwise.
#[inline]
fn sobol_point(index: u32, seeds: &SetSeeds) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    if has_sse41() {
        // SAFETY: the CPU has SSE4.1 and SSSE3.
        return unsafe { sse41::sobol_point(index, seeds) };
    }
    sobol_point_portable(index, seeds)
}

/// [`sobol_point`] with `sobol_burley`'s own 4-lane operations (on baseline x86-64, SSE2: its
/// 32-bit multiplies take five instructions each, its bit reversal 25).
#[inline]
fn sobol_point_portable(index: u32, seeds: &SetSeeds) -> [f32; 4] {
    let rev = parts::owen_scramble_rev(index.reverse_bits(), seeds.shuffle);
    let t = &*SOBOL_TABLES;
    let sobol = Int4::from(t.hi[(rev >> 24) as usize]) ^ Int4::from(t.lo[((rev >> 16) & 0xff) as usize]);
    parts::owen_scramble_int4_rev(sobol, Int4::from(seeds.scramble)).reverse_bits().to_f32_norm()
}

/// The crate's 4-lane steps with SSE4.1's 32-bit multiply and SSSE3's byte shuffle (bit
/// reversal by bytes, then by nibble tables): the same integer operations, so the same bits
/// (`sobol_point_sse41_is_the_portable_one`).
#[cfg(target_arch = "x86_64")]
mod sse41 {
    use std::arch::x86_64::*;

    use super::{parts, SetSeeds, SOBOL_TABLES};

    #[target_feature(enable = "sse4.1,ssse3")]
    pub(super) unsafe fn sobol_point(index: u32, seeds: &SetSeeds) -> [f32; 4] {
        let rev = parts::owen_scramble_rev(index.reverse_bits(), seeds.shuffle);
        let t = &*SOBOL_TABLES;
        let load = |a: &[u32; 4]| _mm_loadu_si128(a.as_ptr().cast());
        let mut n =
            _mm_xor_si128(load(&t.hi[(rev >> 24) as usize]), load(&t.lo[((rev >> 16) & 0xff) as usize]));
        // parts::owen_scramble_int4_rev
        let scramble = load(&seeds.scramble);
        let k = |c: u32| _mm_set1_epi32(c as i32);
        n = _mm_xor_si128(n, _mm_mullo_epi32(n, k(0x3d20_adea)));
        n = _mm_add_epi32(n, scramble);
        n = _mm_mullo_epi32(n, _mm_or_si128(_mm_srli_epi32::<16>(scramble), k(1)));
        n = _mm_xor_si128(n, _mm_mullo_epi32(n, k(0x0552_6c56)));
        n = _mm_xor_si128(n, _mm_mullo_epi32(n, k(0x53a2_2864)));
        // Int4::reverse_bits: the bytes of each lane reversed, then the bits of each byte.
        n = _mm_shuffle_epi8(n, _mm_setr_epi8(3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12));
        let low = _mm_and_si128(n, _mm_set1_epi8(0x0f));
        let high = _mm_and_si128(_mm_srli_epi16::<4>(n), _mm_set1_epi8(0x0f));
        // A nibble reversed: a byte's low nibble becomes its high one, and the other way round.
        let to_low = _mm_setr_epi8(0, 8, 4, 12, 2, 10, 6, 14, 1, 9, 5, 13, 3, 11, 7, 15);
        let to_high = _mm_slli_epi16::<4>(to_low);
        n = _mm_or_si128(_mm_shuffle_epi8(to_high, low), _mm_shuffle_epi8(to_low, high));
        // Int4::to_f32_norm
        let f = _mm_sub_ps(
            _mm_castsi128_ps(_mm_or_si128(_mm_srli_epi32::<9>(n), k(0x3f80_0000))),
            _mm_set1_ps(1.0),
        );
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(out.as_mut_ptr(), f);
        out
    }

    /// [`super::hashed_units_portable`] in four lanes: `hash_u32` of h ^ k 0x9e3779b9 for
    /// k = 1..4, then 24 bits each as a float (exact: below 2^24, signed or not).
    #[target_feature(enable = "sse4.1")]
    pub(super) unsafe fn hashed_units(h: u32) -> [f32; 4] {
        let k = |c: u32| _mm_set1_epi32(c as i32);
        let lanes = |k: u32| k.wrapping_mul(0x9e37_79b9) as i32;
        let mut x = _mm_xor_si128(k(h), _mm_setr_epi32(lanes(1), lanes(2), lanes(3), lanes(4)));
        // crate::math::hash_u32
        x = _mm_xor_si128(x, _mm_srli_epi32::<16>(x));
        x = _mm_mullo_epi32(x, k(0x7feb_352d));
        x = _mm_xor_si128(x, _mm_srli_epi32::<15>(x));
        x = _mm_mullo_epi32(x, k(0x846c_a68b));
        x = _mm_xor_si128(x, _mm_srli_epi32::<16>(x));
        let f = _mm_mul_ps(_mm_cvtepi32_ps(_mm_srli_epi32::<8>(x)), _mm_set1_ps(1.0 / 16_777_216.0));
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(out.as_mut_ptr(), f);
        out
    }
}

/// A 4-D set taken from a [`SampleStream`] and computed on first use.
pub struct Deferred {
    set: u32,
    values: Option<[f32; 4]>,
}

impl Deferred {
    /// The set's values; `s` must be the stream it was taken from.
    #[inline]
    pub fn get(&mut self, s: &SampleStream<'_>) -> [f32; 4] {
        *self.values.get_or_insert_with(|| s.set_4d(self.set))
    }
}

/// Scene loading: every sampler Mitsuba names (`independent`, `stratified`, `multijitter`,
/// `orthogonal`, `ldsampler`) is rendered with Furnace's one sequence; each gives
/// `sample_count` (4) and `seed` (0).
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<(u32, u64)> {
    let spp = b.positive_int(i, "sample_count", 4)?;
    let seed = b.doc.int_or(i, "seed", 0)?;
    Ok((spp, seed as u64))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first `n` sets of sample `index` of pixel `(x, y)`, through a fresh [`PixelSeeds`].
    fn sets(job_seed: u64, x: u32, y: u32, index: u64, n: usize) -> Vec<[f32; 4]> {
        let mut p = PixelSeeds::new(job_seed, x, y);
        let mut s = p.stream(index);
        (0..n).map(|_| s.next_4d()).collect()
    }

    #[test]
    fn samples_depend_only_on_their_coordinates() {
        let a = sets(7, 3, 4, 100, 1)[0];
        let mut p = PixelSeeds::new(7, 3, 4);
        p.stream(99).next_4d();
        let b = p.stream(100).next_4d();
        assert_eq!(a, b);
        assert_ne!(a, sets(7, 4, 3, 100, 1)[0]);
        assert_ne!(a, sets(8, 3, 4, 100, 1)[0]);
    }

    /// The seeds hashed once a pixel give exactly what hashing them for every sample and set
    /// gave (the stream before `PixelSeeds`, written out here from the crate): any index order,
    /// across blocks of the sequence, Sobol sets and hashed ones.
    #[test]
    fn pixel_seeds_give_the_per_sample_hashes() {
        let per_sample = |job: u64, x: u32, y: u32, index: u64, set: u32| -> [f32; 4] {
            let block = (index / SEQUENCE_LEN as u64) as u32;
            let seed = hash_words(&[job as u32, (job >> 32) as u32, x, y, block]);
            let i = (index % SEQUENCE_LEN as u64) as u32;
            if set < SOBOL_SETS {
                return sobol_burley::sample_4d(i, 0, hash_words(&[seed, set]));
            }
            let h = hash_words(&[seed, set, i]);
            let unit =
                |k: u32| (hash_u32(h ^ k.wrapping_mul(0x9e37_79b9)) >> 8) as f32 * (1.0 / 16_777_216.0);
            [unit(1), unit(2), unit(3), unit(4)]
        };
        for (job, x, y) in [(0u64, 0u32, 0u32), (7, 3, 4), (u64::MAX, 1919, 1079), (1 << 40, 5, 9)] {
            let mut p = PixelSeeds::new(job, x, y);
            for index in [0u64, 1, 65_535, 65_536, 3, 200_000, 131_071, 65_536, 0, 1 << 33] {
                let mut s = p.stream(index);
                for set in 0..SOBOL_SETS + 3 {
                    let want = per_sample(job, x, y, index, set).map(f32::to_bits);
                    assert_eq!(s.next_4d().map(f32::to_bits), want, "{job} ({x}, {y}) {index} set {set}");
                }
            }
        }
    }

    /// A deferred set has the values `next_4d` would have given it, whenever it is computed,
    /// and sets after it are the same whether or not it was.
    #[test]
    fn deferred_sets_match_drawn_ones() {
        for index in [0u64, 5, 70_000] {
            let all = sets(3, 1, 2, index, SOBOL_SETS as usize + 2);
            let mut p = PixelSeeds::new(3, 1, 2);
            let mut s = p.stream(index);
            assert_eq!(s.next_4d(), all[0]);
            let mut d1 = s.defer_4d();
            let _unused = s.defer_4d();
            assert_eq!(s.next_4d(), all[3]);
            assert_eq!(d1.get(&s), all[1]);
            assert_eq!(d1.get(&s), all[1]);
            while s.set < SOBOL_SETS {
                s.skip_4d();
            }
            let mut late = s.defer_4d(); // a hashed set (past SOBOL_SETS)
            assert_eq!(s.next_4d(), all[SOBOL_SETS as usize + 1]);
            assert_eq!(late.get(&s), all[SOBOL_SETS as usize]);
        }
    }

    /// A set peeked at is the one `next_4d` draws, until `skip_4d` takes it; peeking twice
    /// changes nothing (the integrator peeks before the pass through hidden emitters, which
    /// takes no set). Sobol sets and hashed ones.
    #[test]
    fn peeked_sets_are_the_drawn_ones() {
        for index in [0u64, 5, 70_000] {
            let all = sets(3, 1, 2, index, SOBOL_SETS as usize + 4);
            let mut p = PixelSeeds::new(3, 1, 2);
            let mut s = p.stream(index);
            for (k, want) in all.iter().enumerate() {
                assert_eq!(s.peek_4d(), *want, "set {k}");
                if k + 2 < all.len() {
                    assert_eq!(s.peek_4d_ahead(2), all[k + 2], "set {k} + 2, peeked ahead");
                }
                assert_eq!(s.peek_4d(), *want, "set {k}, peeked again");
                if k % 2 == 0 {
                    s.skip_4d();
                } else {
                    assert_eq!(s.next_4d(), *want, "set {k}");
                }
            }
            // The integrator's order at a vertex: peek this vertex's set and the next vertex's,
            // skip, then defer the choices' set; the next vertex's is then the next set.
            let mut p = PixelSeeds::new(3, 1, 2);
            let mut s = p.stream(index);
            let (first, ahead) = (s.peek_4d(), s.peek_4d_ahead(2));
            s.skip_4d();
            let mut deferred = s.defer_4d();
            assert_eq!((first, ahead, s.peek_4d()), (all[0], all[2], all[2]));
            assert_eq!((s.next_4d(), deferred.get(&s)), (all[2], all[1]));
        }
    }

    /// The table-driven set is the crate's, bit for bit: every index of the sequence, for
    /// several seeds.
    #[test]
    fn sobol_set0_is_sobol_burleys() {
        for seed in [0u32, 1, 0x9e37_79b9, 0xdead_beef, u32::MAX] {
            for index in 0..SEQUENCE_LEN {
                let (a, b) = (sobol_set0(index, seed), sobol_burley::sample_4d(index, 0, seed));
                assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "index {index}, seed {seed:#x}");
            }
        }
    }

    /// The SSE4.1 steps give the portable ones' bits: every index, for several seeds.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn sobol_point_sse41_is_the_portable_one() {
        if !has_sse41() {
            return; // nothing to compare on this CPU
        }
        for seed in [0u32, 7, 0x9e37_79b9, 0xdead_beef, u32::MAX] {
            let seeds = SetSeeds::new(seed);
            for index in 0..SEQUENCE_LEN {
                // SAFETY: checked above.
                let fast = unsafe { sse41::sobol_point(index, &seeds) };
                let portable = sobol_point_portable(index, &seeds);
                assert_eq!(
                    fast.map(f32::to_bits),
                    portable.map(f32::to_bits),
                    "index {index}, seed {seed:#x}"
                );
            }
        }
    }

    /// The SSE4.1 hashed set is the portable one, bit for bit: hashes of every bit pattern's
    /// neighbourhood (zero, all ones, single bits) and a million others.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn hashed_units_sse41_are_the_portable_ones() {
        if !has_sse41() {
            return; // nothing to compare on this CPU
        }
        let special = [0u32, u32::MAX, 0x8000_0000, 0x7fff_ffff].into_iter().chain((0..32).map(|b| 1 << b));
        for h in special.chain((0..1_000_000u32).map(|i| hash_u32(i).wrapping_add(i))) {
            // SAFETY: checked above.
            let fast = unsafe { sse41::hashed_units(h) };
            assert_eq!(fast.map(f32::to_bits), hashed_units_portable(h).map(f32::to_bits), "{h:#x}");
            assert!(fast.iter().all(|u| (0.0..1.0).contains(u)));
        }
    }

    #[test]
    fn hash_words_continue_from_a_state() {
        for words in [&[][..], &[7], &[1, 2], &[u32::MAX, 0, 5], &[9, 8, 7, 6, 5]] {
            assert_eq!(words.iter().fold(HASH_START, |h, &w| hash_step(h, w)), hash_words(words));
        }
        assert_ne!(hash_words(&[1, 2]), hash_words(&[2, 1]));
    }

    #[test]
    fn first_dimensions_are_stratified() {
        // 2^k points of an Owen-scrambled Sobol set put exactly one point in each 1/2^k stratum.
        let n = 256;
        let mut seen = vec![false; n];
        let mut p = PixelSeeds::new(1, 10, 20);
        for i in 0..n as u64 {
            let v = p.stream(i).next_4d();
            for c in v {
                assert!((0.0..1.0).contains(&c));
            }
            seen[(v[0] * n as f32) as usize] = true;
        }
        assert!(seen.iter().all(|&s| s));
    }
}
