//! The instructions this build was compiled to assume, and whether this CPU runs them.
//!
//! On x86-64 the repository's `.cargo/config.toml` builds for x86-64-v2 (SSE3, SSSE3, SSE4.1,
//! SSE4.2, POPCNT, CMPXCHG16B: Intel Core since Nehalem, 2008, Atom since 2013; AMD since
//! Bulldozer, 2011) instead of the 2003 baseline (SSE2): the whole renderer, not only the
//! kernels chosen at run time, may then use SSE4.1's rounding, blends and shuffles. A plain
//! release build renders 2-15% more samples a second; a profile-guided one within 1% of what
//! it did (docs/BENCHMARKS.md, "Issue 15, nineteenth step"). The floating-point operations
//! are the same (no contraction into FMA, the same roundings), so such a build renders the
//! baseline build's bytes. A CPU without these instructions would stop at the first one;
//! [`missing`] lets the binary say so before.

/// Each x86 feature this build was compiled to assume (a `target_feature` on at compile time,
/// beyond x86-64's SSE2, among those that `cfg!` reports on stable Rust: x86-64-v2's LAHF/SAHF
/// is not, and every CPU with SSSE3 has it) and whether this CPU has it. (Not `is_x86_feature_detected!`: for a
/// feature enabled at compile time it answers true without asking the CPU.)
#[cfg(target_arch = "x86_64")]
fn assumed() -> Vec<(&'static str, bool)> {
    let cpu = Cpuid::read();
    let mut out = Vec::new();
    macro_rules! check {
        ($($f:tt),*) => {$(
            if cfg!(target_feature = $f) {
                out.push(($f, cpu.has($f)));
            }
        )*};
    }
    check!(
        "sse3",
        "ssse3",
        "sse4.1",
        "sse4.2",
        "popcnt",
        "cmpxchg16b",
        "avx",
        "avx2",
        "fma",
        "bmi1",
        "bmi2",
        "lzcnt",
        "movbe",
        "f16c",
        "avx512f",
        "avx512bw",
        "avx512cd",
        "avx512dq",
        "avx512vl"
    );
    out
}

/// The CPUID bits that say which of those features this CPU has, and whether the operating
/// system saves the AVX and AVX-512 registers (XCR0).
#[cfg(target_arch = "x86_64")]
struct Cpuid {
    ecx1: u32,
    ebx7: u32,
    ecx_ext: u32,
    ymm: bool,
    zmm: bool,
}

#[cfg(target_arch = "x86_64")]
impl Cpuid {
    fn read() -> Cpuid {
        use std::arch::x86_64::{__cpuid, __cpuid_count};
        // SAFETY: CPUID exists on every x86-64 CPU; leaves past the maximum are not read.
        // (Recent Rust has made these functions safe; older toolchains need the block.)
        #[allow(unused_unsafe)]
        let (ecx1, ebx7, ecx_ext) = unsafe {
            let (max, max_ext) = (__cpuid(0).eax, __cpuid(0x8000_0000).eax);
            (
                if max >= 1 { __cpuid(1).ecx } else { 0 },
                if max >= 7 { __cpuid_count(7, 0).ebx } else { 0 },
                if max_ext >= 0x8000_0001 { __cpuid(0x8000_0001).ecx } else { 0 },
            )
        };
        // XCR0, readable where the OS has enabled XSAVE (OSXSAVE, leaf 1 ECX bit 27).
        let xcr0 = if ecx1 >> 27 & 1 != 0 {
            let (lo, _hi): (u32, u32);
            // SAFETY: XGETBV with ECX 0 is available when OSXSAVE is set.
            unsafe {
                std::arch::asm!("xgetbv", in("ecx") 0, out("eax") lo, out("edx") _hi,
                    options(nomem, nostack, preserves_flags));
            }
            lo
        } else {
            0
        };
        Cpuid { ecx1, ebx7, ecx_ext, ymm: xcr0 & 0b110 == 0b110, zmm: xcr0 & 0b1110_0110 == 0b1110_0110 }
    }

    /// Whether the CPU (and for AVX and AVX-512, the OS) runs feature `f`.
    fn has(&self, f: &str) -> bool {
        let bit = |r: u32, b: u32| r >> b & 1 != 0;
        let (c, b) = (self.ecx1, self.ebx7);
        match f {
            "sse3" => bit(c, 0),
            "ssse3" => bit(c, 9),
            "fma" => bit(c, 12) && self.ymm,
            "cmpxchg16b" => bit(c, 13),
            "sse4.1" => bit(c, 19),
            "sse4.2" => bit(c, 20),
            "movbe" => bit(c, 22),
            "popcnt" => bit(c, 23),
            "avx" => bit(c, 28) && self.ymm,
            "f16c" => bit(c, 29) && self.ymm,
            "bmi1" => bit(b, 3),
            "avx2" => bit(b, 5) && self.ymm,
            "bmi2" => bit(b, 8),
            "avx512f" => bit(b, 16) && self.zmm,
            "avx512dq" => bit(b, 17) && self.zmm,
            "avx512cd" => bit(b, 28) && self.zmm,
            "avx512bw" => bit(b, 30) && self.zmm,
            "avx512vl" => bit(b, 31) && self.zmm,
            "lzcnt" => bit(self.ecx_ext, 5),
            _ => false,
        }
    }
}

/// The compile-time features this CPU lacks (none where the binary runs here).
pub fn missing() -> Vec<&'static str> {
    #[cfg(target_arch = "x86_64")]
    return assumed().into_iter().filter(|&(_, has)| !has).map(|(f, _)| f).collect();
    #[cfg(not(target_arch = "x86_64"))]
    Vec::new()
}

/// What this build was compiled for: `x86-64-v2`, `x86-64-v3`, `x86-64-v4`, or (for builds
/// without the repository's config, as with a `RUSTFLAGS` of one's own) `x86-64` plus the
/// features it assumes, or the architecture elsewhere.
pub fn build_target() -> String {
    #[cfg(target_arch = "x86_64")]
    {
        let has = |f: &str| assumed().iter().any(|&(g, _)| g == f);
        let v2 = ["sse3", "ssse3", "sse4.1", "sse4.2", "popcnt"].iter().all(|f| has(f));
        let v3 =
            v2 && ["avx", "avx2", "fma", "bmi1", "bmi2", "lzcnt", "movbe", "f16c"].iter().all(|f| has(f));
        let v4 = v3 && ["avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"].iter().all(|f| has(f));
        match (v4, v3, v2) {
            (true, _, _) => "x86-64-v4".into(),
            (_, true, _) => "x86-64-v3".into(),
            (_, _, true) => "x86-64-v2".into(),
            _ => {
                let extra: Vec<_> = assumed().into_iter().map(|(f, _)| f).collect();
                if extra.is_empty() {
                    "x86-64".into()
                } else {
                    format!("x86-64 with {}", extra.join(", "))
                }
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    std::env::consts::ARCH.into()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The CPU running the tests runs what the build assumes, and the build is named by the
    /// features it assumes (x86-64-v2 under the repository's `.cargo/config.toml`; a
    /// `RUSTFLAGS` of one's own replaces that config, and names another level).
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn this_cpu_runs_what_the_build_assumes() {
        assert!(missing().is_empty(), "this CPU lacks {:?}", missing());
        let v2 = cfg!(all(
            target_feature = "sse3",
            target_feature = "ssse3",
            target_feature = "sse4.1",
            target_feature = "sse4.2",
            target_feature = "popcnt"
        ));
        let avx = cfg!(target_feature = "avx");
        match (v2, avx) {
            (true, false) => assert_eq!(build_target(), "x86-64-v2"),
            (false, false) if !cfg!(target_feature = "sse3") => assert_eq!(build_target(), "x86-64"),
            _ => assert!(build_target().starts_with("x86-64"), "{}", build_target()),
        }
    }

    /// The CPUID reading agrees with the standard library's detection on every feature that
    /// this build does not assume (for those, std answers at compile time).
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn cpuid_agrees_with_runtime_detection() {
        let cpu = Cpuid::read();
        macro_rules! agree {
            ($($f:tt),*) => {$(
                if !cfg!(target_feature = $f) {
                    assert_eq!(cpu.has($f), std::is_x86_feature_detected!($f), "{}", $f);
                }
            )*};
        }
        agree!(
            "sse3",
            "ssse3",
            "sse4.1",
            "sse4.2",
            "popcnt",
            "cmpxchg16b",
            "avx",
            "avx2",
            "fma",
            "bmi1",
            "bmi2",
            "lzcnt",
            "movbe",
            "f16c",
            "avx512f",
            "avx512bw",
            "avx512cd",
            "avx512dq",
            "avx512vl"
        );
        // And where the build assumes a feature, CPUID must say this CPU has it.
        for (f, has) in assumed() {
            assert!(has && cpu.has(f), "{f}");
        }
    }
}
