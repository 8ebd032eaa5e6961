//! The instructions this build was compiled to assume, and whether this CPU runs them.
//!
//! On x86-64 the repository's `.cargo/config.toml` builds for x86-64-v2 (SSE3, SSSE3, SSE4.1,
//! SSE4.2, POPCNT, CMPXCHG16B: Intel Core since Nehalem, 2008, Atom since 2013; AMD since
//! Bulldozer, 2011) instead of the 2003 baseline (SSE2): the whole renderer, not only the
//! kernels chosen at run time, may then use SSE4.1's rounding, blends and shuffles. A plain
//! release build renders 2-15% more samples a second; a profile-guided one -0.6% to +1.2%
//! of what it did (docs/BENCHMARKS.md, "Issue 15, nineteenth step"). The floating-point operations
//! are the same (no contraction into FMA, the same roundings), so such a build renders the
//! baseline build's bytes. A CPU without these instructions would stop at the first one;
//! [`supported`] and [`refuse`] let the binary say so before. They know the features of
//! x86-64-v2, v3 and v4; a build for one CPU (`target-cpu=native`) may assume more, and
//! toolchains before Rust 1.89 do not report AVX-512 to `cfg!`.

/// One x86 feature: its name, the x86-64 level (2, 3 or 4) it belongs to, where CPUID reports
/// it, and whether the OS must also save the AVX (`Os::Ymm`) or AVX-512 (`Os::Zmm`) registers
/// for it.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct Feature {
    name: &'static str,
    level: u32,
    reg: Reg,
    bit: u32,
    os: Os,
    /// Whether this build was compiled to assume it (`target_feature` on at compile time).
    assumed: bool,
}

/// A CPUID register: leaf 1 ECX, leaf 7 (subleaf 0) EBX, leaf 0x8000_0001 ECX.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy, PartialEq, Eq)]
enum Reg {
    Ecx1,
    Ebx7,
    EcxExt,
}

#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy, PartialEq, Eq)]
enum Os {
    None,
    Ymm,
    Zmm,
}

/// Invokes macro `$m` with every x86 feature this module checks (beyond x86-64's SSE2, among
/// those that `cfg!` reports on stable Rust: x86-64-v2's LAHF/SAHF is not, and every CPU with
/// SSSE3 has it), as `name level reg bit os` tuples.
#[cfg(target_arch = "x86_64")]
macro_rules! x86_features {
    ($m:ident) => {
        $m!(
            ("sse3", 2, Ecx1, 0, None),
            ("ssse3", 2, Ecx1, 9, None),
            ("sse4.1", 2, Ecx1, 19, None),
            ("sse4.2", 2, Ecx1, 20, None),
            ("popcnt", 2, Ecx1, 23, None),
            ("cmpxchg16b", 2, Ecx1, 13, None),
            ("avx", 3, Ecx1, 28, Ymm),
            ("avx2", 3, Ebx7, 5, Ymm),
            ("fma", 3, Ecx1, 12, Ymm),
            ("bmi1", 3, Ebx7, 3, None),
            ("bmi2", 3, Ebx7, 8, None),
            ("lzcnt", 3, EcxExt, 5, None),
            ("movbe", 3, Ecx1, 22, None),
            ("f16c", 3, Ecx1, 29, Ymm),
            ("avx512f", 4, Ebx7, 16, Zmm),
            ("avx512bw", 4, Ebx7, 30, Zmm),
            ("avx512cd", 4, Ebx7, 28, Zmm),
            ("avx512dq", 4, Ebx7, 17, Zmm),
            ("avx512vl", 4, Ebx7, 31, Zmm)
        )
    };
}

#[cfg(target_arch = "x86_64")]
macro_rules! feature_table {
    ($(($f:tt, $l:expr, $r:ident, $b:expr, $o:ident)),*) => {
        [$(Feature { name: $f, level: $l, reg: Reg::$r, bit: $b, os: Os::$o, assumed: cfg!(target_feature = $f) }),*]
    };
}

#[cfg(target_arch = "x86_64")]
const FEATURES: [Feature; 19] = x86_features!(feature_table);

/// The CPUID bits (and OS register state) that this build assumes, from [`FEATURES`].
#[cfg(target_arch = "x86_64")]
const REQUIRED: Cpuid = {
    let mut r = Cpuid { ecx1: 0, ebx7: 0, ecx_ext: 0, ymm: false, zmm: false };
    let mut i = 0;
    while i < FEATURES.len() {
        let f = FEATURES[i];
        if f.assumed {
            match f.reg {
                Reg::Ecx1 => r.ecx1 |= 1 << f.bit,
                Reg::Ebx7 => r.ebx7 |= 1 << f.bit,
                Reg::EcxExt => r.ecx_ext |= 1 << f.bit,
            }
            r.ymm |= matches!(f.os, Os::Ymm | Os::Zmm);
            r.zmm |= matches!(f.os, Os::Zmm);
        }
        i += 1;
    }
    r
};

/// Whether this CPU runs every instruction this build was compiled to assume. Integer work
/// on CPUID's registers only: it runs before `main` does anything else, and on a CPU without
/// those instructions it must not use them itself (with AVX assumed, the compiler writes even
/// plain copies of 16 bytes in AVX).
#[inline(never)]
pub fn supported() -> bool {
    #[cfg(target_arch = "x86_64")]
    return supported_by(&Cpuid::read());
    #[cfg(not(target_arch = "x86_64"))]
    true
}

/// [`supported`] on the CPU that `c` describes.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn supported_by(c: &Cpuid) -> bool {
    let r = REQUIRED;
    c.ecx1 & r.ecx1 == r.ecx1
        && c.ebx7 & r.ebx7 == r.ebx7
        && c.ecx_ext & r.ecx_ext == r.ecx_ext
        && (c.ymm || !r.ymm)
        && (c.zmm || !r.zmm)
}

/// What a binary says, and does, on a CPU that is not [`supported`]: a fixed message (no
/// formatting, which could use the instructions that are missing) and exit status 1.
#[cold]
#[inline(never)]
pub fn refuse() -> ! {
    use std::io::Write;
    let mut err = std::io::stderr();
    let _ = err.write_all(b"error: this furnace was built for ");
    let _ = err.write_all(BUILD_LEVEL.as_bytes());
    let _ = err.write_all(
        b" and this CPU lacks some of those instructions; build it for this CPU with \
          RUSTFLAGS=\"-C target-cpu=native\" cargo build --release (or target-cpu=x86-64 for any x86-64)\n",
    );
    std::process::exit(1)
}

/// Whether this build assumes every feature of x86-64 levels 2 to `level`.
#[cfg(target_arch = "x86_64")]
const fn assumes_level(level: u32) -> bool {
    let mut i = 0;
    while i < FEATURES.len() {
        if FEATURES[i].level <= level && !FEATURES[i].assumed {
            return false;
        }
        i += 1;
    }
    true
}
#[cfg(not(target_arch = "x86_64"))]
const fn assumes_level(_: u32) -> bool {
    false
}
const V2: bool = assumes_level(2);

/// [`build_target`]'s level, fixed at compile time.
const BUILD_LEVEL: &str = if cfg!(not(target_arch = "x86_64")) {
    std::env::consts::ARCH
} else if assumes_level(4) {
    "x86-64-v4"
} else if assumes_level(3) {
    "x86-64-v3"
} else if V2 {
    "x86-64-v2"
} else {
    "x86-64"
};

/// The CPUID bits that say which features this CPU has, and whether the operating system
/// saves the AVX and AVX-512 registers (XCR0).
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct Cpuid {
    ecx1: u32,
    ebx7: u32,
    ecx_ext: u32,
    ymm: bool,
    zmm: bool,
}

#[cfg(target_arch = "x86_64")]
impl Cpuid {
    #[inline(always)]
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
        let (ymm, zmm) = os_saves(xcr0);
        Cpuid { ecx1, ebx7, ecx_ext, ymm, zmm }
    }

    /// Whether the CPU (and for AVX and AVX-512, the OS) runs feature `f`.
    #[cfg(test)]
    fn has(&self, f: &Feature) -> bool {
        let r = match f.reg {
            Reg::Ecx1 => self.ecx1,
            Reg::Ebx7 => self.ebx7,
            Reg::EcxExt => self.ecx_ext,
        };
        let os = match f.os {
            Os::None => true,
            Os::Ymm => self.ymm,
            Os::Zmm => self.zmm,
        };
        r >> f.bit & 1 != 0 && os
    }
}

/// Whether the OS saves the AVX registers (XCR0 bits 1 and 2: SSE and AVX state) and the
/// AVX-512 ones as well (bits 5, 6 and 7: opmask, upper halves of ZMM0-15, ZMM16-31).
#[cfg(target_arch = "x86_64")]
fn os_saves(xcr0: u32) -> (bool, bool) {
    let ymm = xcr0 & 0b110 == 0b110;
    (ymm, ymm && xcr0 & 0b1110_0000 == 0b1110_0000)
}

/// What this build was compiled for: `x86-64-v2`, `x86-64-v3`, `x86-64-v4`, or (for builds
/// without the repository's config, as with a `RUSTFLAGS` of one's own) `x86-64` plus the
/// features it assumes, or the architecture elsewhere.
pub fn build_target() -> String {
    #[cfg(target_arch = "x86_64")]
    if !V2 {
        let extra: Vec<_> = FEATURES.iter().filter(|f| f.assumed).map(|f| f.name).collect();
        if !extra.is_empty() {
            return format!("x86-64 with {}", extra.join(", "));
        }
    }
    BUILD_LEVEL.into()
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    /// Each x86 feature this build was compiled to assume and whether the CPU `c` describes has it.
    fn assumed(c: &Cpuid) -> Vec<(&'static str, bool)> {
        FEATURES.iter().filter(|f| f.assumed).map(|f| (f.name, c.has(f))).collect()
    }

    /// The features this build assumes that the CPU `c` describes lacks.
    fn lacking(c: &Cpuid) -> Vec<&'static str> {
        assumed(c).into_iter().filter(|&(_, has)| !has).map(|(f, _)| f).collect()
    }

    /// The CPU running the tests runs what the build assumes, and the build is named by the
    /// features it assumes (x86-64-v2 under the repository's `.cargo/config.toml`; a
    /// `RUSTFLAGS` of one's own replaces that config, and names another level).
    #[test]
    fn this_cpu_runs_what_the_build_assumes() {
        let lacks = lacking(&Cpuid::read());
        assert!(supported() && lacks.is_empty(), "this CPU lacks {lacks:?}");
        match (V2, cfg!(target_feature = "avx")) {
            (true, false) => assert_eq!(build_target(), "x86-64-v2"),
            (false, false) if !cfg!(target_feature = "sse3") => assert_eq!(build_target(), "x86-64"),
            _ => assert!(build_target().starts_with("x86-64"), "{}", build_target()),
        }
    }

    /// Each assumed feature taken from this CPU's CPUID (its bit cleared, or for AVX and
    /// AVX-512 the OS's register state) makes the CPU unsupported, and is the one missing.
    #[test]
    fn a_cpu_without_an_assumed_feature_is_refused() {
        let real = Cpuid::read();
        assert!(supported_by(&real));
        for f in FEATURES.iter().filter(|f| f.assumed) {
            let mut c = real;
            match f.reg {
                Reg::Ecx1 => c.ecx1 &= !(1 << f.bit),
                Reg::Ebx7 => c.ebx7 &= !(1 << f.bit),
                Reg::EcxExt => c.ecx_ext &= !(1 << f.bit),
            }
            let lacks = lacking(&c);
            assert!(!supported_by(&c) && lacks == [f.name], "{}: {lacks:?}", f.name);
            // Without the OS's register state: AVX's for both kinds, AVX-512's for AVX-512.
            for (ymm, zmm) in [(false, real.zmm), (real.ymm, false)] {
                let c = Cpuid { ymm, zmm, ..real };
                let lacks = lacking(&c);
                let named = lacks.contains(&f.name);
                let needs = f.os == Os::Zmm || (f.os == Os::Ymm && !ymm);
                assert_eq!(named, needs, "{}: ymm {ymm} zmm {zmm}", f.name);
                assert!(supported_by(&c) == lacks.is_empty(), "{}: ymm {ymm} zmm {zmm}", f.name);
            }
        }
    }

    /// No two features read the same CPUID bit (a copied line that kept its bit would pass
    /// the comparisons below on a CPU that has both features).
    #[test]
    fn each_feature_has_its_own_bit() {
        for (i, f) in FEATURES.iter().enumerate() {
            for g in &FEATURES[i + 1..] {
                assert!(f.name != g.name && (f.reg != g.reg || f.bit != g.bit), "{} and {}", f.name, g.name);
            }
        }
    }

    #[test]
    fn xcr0_says_which_registers_the_os_saves() {
        assert_eq!(os_saves(0b11), (false, false)); // x87 and SSE only
        assert_eq!(os_saves(0b111), (true, false)); // and AVX
        assert_eq!(os_saves(0b1110_0111), (true, true)); // and AVX-512
        assert_eq!(os_saves(0b1110_0011), (false, false)); // AVX-512 state without AVX's
        assert_eq!(os_saves(0b0110_0111), (true, false)); // ZMM16-31 not saved
        assert_eq!(os_saves(0b1100_0111), (true, false)); // opmask not saved
    }

    /// Every feature of the table against the kernel's own reading of CPUID (/proc/cpuinfo's
    /// flags), the features this build assumes included.
    #[test]
    fn cpuid_agrees_with_the_kernels_flags() {
        let Ok(info) = std::fs::read_to_string("/proc/cpuinfo") else {
            return; // not Linux: the test below still compares with std's detection
        };
        let flags: Vec<&str> = info
            .lines()
            .find_map(|l| l.strip_prefix("flags"))
            .and_then(|l| l.split_once(':'))
            .map(|(_, f)| f.split_whitespace().collect())
            .unwrap_or_default();
        assert!(flags.contains(&"sse2"), "no flags line in /proc/cpuinfo");
        let linux = |f: &'static str| match f {
            "sse3" => "pni",
            "sse4.1" => "sse4_1",
            "sse4.2" => "sse4_2",
            "cmpxchg16b" => "cx16",
            "lzcnt" => "abm",
            f => f,
        };
        let cpu = Cpuid::read();
        for f in FEATURES {
            // (The kernel lists AVX features only where it saves their registers too.)
            assert_eq!(cpu.has(&f), flags.contains(&linux(f.name)), "{}", f.name);
        }
    }

    /// The CPUID reading agrees with the standard library's detection on every feature that
    /// this build does not assume (for those, std answers at compile time).
    #[test]
    fn cpuid_agrees_with_runtime_detection() {
        let cpu = Cpuid::read();
        macro_rules! agree {
            ($(($f:tt, $l:expr, $r:ident, $b:expr, $o:ident)),*) => {$(
                if !cfg!(target_feature = $f) {
                    let f = FEATURES.iter().find(|g| g.name == $f).unwrap();
                    assert_eq!(cpu.has(f), std::is_x86_feature_detected!($f), "{}", $f);
                }
            )*};
        }
        x86_features!(agree);
        // And where the build assumes a feature, CPUID must say this CPU has it.
        for (f, has) in assumed(&cpu) {
            assert!(has, "{f}");
        }
    }
}
