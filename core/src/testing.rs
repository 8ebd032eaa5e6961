//! Statistical test helpers: a chi-square goodness-of-fit test of a direction sampler against
//! its pdf over the sphere (Mitsuba's recipe: cells with fewer than 5 expected samples are
//! pooled, significance 1% with Sidak correction over all tests of a suite), and a small
//! deterministic random number generator.

use glam::{Vec2, Vec3};

/// PCG32 (O'Neill 2014): deterministic uniform numbers for tests.
pub struct Pcg(u64);

impl Pcg {
    pub fn new(seed: u64) -> Pcg {
        let mut p = Pcg(seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407));
        p.next_u32();
        p
    }

    pub fn next_u32(&mut self) -> u32 {
        let old = self.0;
        self.0 = old.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        xorshifted.rotate_right((old >> 59) as u32)
    }

    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / 16_777_216.0)
    }

    pub fn next_2d(&mut self) -> Vec2 {
        Vec2::new(self.next_f32(), self.next_f32())
    }
}

/// Direction of (cos theta, phi) on the unit sphere.
fn dir(c: f64, phi: f64) -> Vec3 {
    let s = (1.0 - c * c).max(0.0).sqrt();
    Vec3::new((s * phi.cos()) as f32, (s * phi.sin()) as f32, c as f32)
}

/// Adaptive Simpson integration of f over [a, b].
fn simpson(f: &mut dyn FnMut(f64) -> f64, a: f64, b: f64, eps: f64, depth: u32) -> f64 {
    #[allow(clippy::too_many_arguments)] // a recursion carrying its interval and samples
    fn rec(
        f: &mut dyn FnMut(f64) -> f64,
        a: f64,
        b: f64,
        fa: f64,
        fm: f64,
        fb: f64,
        whole: f64,
        eps: f64,
        depth: u32,
    ) -> f64 {
        let m = 0.5 * (a + b);
        let (lm, rm) = (0.5 * (a + m), 0.5 * (m + b));
        let (flm, frm) = (f(lm), f(rm));
        let left = (m - a) / 6.0 * (fa + 4.0 * flm + fm);
        let right = (b - m) / 6.0 * (fm + 4.0 * frm + fb);
        let delta = left + right - whole;
        if depth == 0 || delta.abs() <= 15.0 * eps {
            return left + right + delta / 15.0;
        }
        rec(f, a, m, fa, flm, fm, left, eps * 0.5, depth - 1)
            + rec(f, m, b, fm, frm, fb, right, eps * 0.5, depth - 1)
    }
    let (fa, fm, fb) = (f(a), f(0.5 * (a + b)), f(b));
    let whole = (b - a) / 6.0 * (fa + 4.0 * fm + fb);
    rec(f, a, b, fa, fm, fb, whole, eps, depth)
}

/// ln Gamma(x) (Lanczos approximation, g = 7, 9 terms).
fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        return (std::f64::consts::PI / (std::f64::consts::PI * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Upper regularised incomplete gamma Q(a, x) = Gamma(a, x) / Gamma(a): series below a + 1,
/// Lentz's continued fraction above.
pub fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let gln = ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut term, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..10_000 {
            ap += 1.0;
            term *= x / ap;
            sum += term;
            if term.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        1.0 - sum * (-x + a * x.ln() - gln).exp()
    } else {
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..10_000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        (-x + a * x.ln() - gln).exp() * h
    }
}

/// Outcome of [`chi2_test`].
#[derive(Debug)]
pub struct Chi2 {
    pub statistic: f64,
    pub dof: usize,
    pub p_value: f64,
    /// Integral of the pdf over the sphere (1 minus the mass the sampler may lose).
    pub pdf_integral: f64,
    /// Fraction of samples the sampler returned (not lost, not delta).
    pub sampled_fraction: f64,
}

/// The histogram grid of [`chi2_test`]: polar cells around `axis`, theta edges at
/// pi (k / rows)^power (power > 1 makes cells near the axis small, to resolve a narrow lobe
/// centred there), `cols` equal phi sectors.
#[derive(Clone, Copy, Debug)]
pub struct Grid {
    pub axis: Vec3,
    pub rows: usize,
    pub cols: usize,
    pub power: f64,
}

impl Grid {
    pub fn uniform(rows: usize, cols: usize) -> Grid {
        Grid { axis: Vec3::Z, rows, cols, power: 1.0 }
    }

    fn theta_edge(&self, k: usize) -> f64 {
        std::f64::consts::PI * (k as f64 / self.rows as f64).powf(self.power)
    }
}

/// Draws `n` directions from `sample` (`None`: no sample, or a delta lobe, both excluded),
/// keeps those inside `region`, histograms them over `grid`, and compares against `n` x the
/// integral of `pdf` x `region` over each cell (adaptive Simpson in theta and phi).
pub fn chi2_test(
    n: usize,
    grid: Grid,
    seed: u64,
    mut sample: impl FnMut(&mut Pcg) -> Option<Vec3>,
    mut pdf: impl FnMut(Vec3) -> f64,
    region: impl Fn(Vec3) -> bool,
) -> Chi2 {
    let frame = crate::math::Frame::from_normal(grid.axis.normalize());
    let (rows, cols) = (grid.rows, grid.cols);
    let tau = 2.0 * std::f64::consts::PI;
    let mut rng = Pcg::new(seed);
    let mut observed = vec![0.0f64; rows * cols];
    let mut got = 0usize;
    for _ in 0..n {
        if let Some(w) = sample(&mut rng) {
            if !region(w) {
                continue;
            }
            got += 1;
            let l = frame.to_local(w);
            let theta = ((l.x as f64).hypot(l.y as f64)).atan2(l.z as f64);
            let mut phi = (l.y as f64).atan2(l.x as f64);
            if phi < 0.0 {
                phi += tau;
            }
            let r = (0..rows).find(|&r| theta < grid.theta_edge(r + 1)).unwrap_or(rows - 1);
            let k = ((phi / tau * cols as f64) as usize).min(cols - 1);
            observed[r * cols + k] += 1.0;
        }
    }
    let mut expected = vec![0.0f64; rows * cols];
    let mut integral = 0.0;
    for r in 0..rows {
        let (t0, t1) = (grid.theta_edge(r), grid.theta_edge(r + 1));
        for k in 0..cols {
            let (p0, p1) = (tau * k as f64 / cols as f64, tau * (k + 1) as f64 / cols as f64);
            let mut outer = |t: f64| {
                let mut inner = |phi: f64| {
                    let l = dir(t.cos(), phi);
                    let w = frame.to_world(l);
                    if region(w) {
                        pdf(w) * t.sin()
                    } else {
                        0.0
                    }
                };
                simpson(&mut inner, p0, p1, 1e-7, 9)
            };
            let e = simpson(&mut outer, t0, t1, 1e-7, 9);
            integral += e;
            expected[r * cols + k] = e * n as f64;
        }
    }
    // Pool cells with fewer than 5 expected samples.
    let mut order: Vec<usize> = (0..rows * cols).collect();
    order.sort_by(|&a, &b| expected[a].total_cmp(&expected[b]));
    let (mut pool_obs, mut pool_exp) = (0.0, 0.0);
    let (mut stat, mut cells) = (0.0, 0usize);
    for &i in &order {
        if expected[i] < 5.0 || pool_exp > 0.0 && pool_exp < 5.0 {
            pool_obs += observed[i];
            pool_exp += expected[i];
            continue;
        }
        stat += (observed[i] - expected[i]).powi(2) / expected[i];
        cells += 1;
    }
    if pool_exp > 0.0 {
        stat += (pool_obs - pool_exp).powi(2) / pool_exp.max(1e-300);
        cells += 1;
    }
    let dof = cells.saturating_sub(1).max(1);
    Chi2 {
        statistic: stat,
        dof,
        p_value: gamma_q(dof as f64 * 0.5, stat * 0.5),
        pdf_integral: integral,
        sampled_fraction: got as f64 / n as f64,
    }
}

/// Significance for one of `tests` tests so that the suite is at 1% (Sidak correction).
pub fn sidak_alpha(tests: usize) -> f64 {
    1.0 - 0.99f64.powf(1.0 / tests as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gamma_q_matches_known_values() {
        // Q(1, x) = exp(-x); chi-square with 2 dof at 5.991 has p = 0.05.
        assert!((gamma_q(1.0, 2.0) - (-2.0f64).exp()).abs() < 1e-12);
        assert!((gamma_q(1.0, 5.991 / 2.0) - 0.05).abs() < 1e-4);
        // chi-square 10 dof at 23.209: p = 0.01.
        assert!((gamma_q(5.0, 23.209 / 2.0) - 0.01).abs() < 1e-4);
    }

    #[test]
    fn chi2_accepts_a_correct_sampler_and_rejects_a_wrong_one() {
        let cos_pdf = |w: Vec3| (w.z.max(0.0) as f64) / std::f64::consts::PI;
        let g = Grid::uniform(10, 20);
        let good = chi2_test(
            100_000,
            g,
            1,
            |r| Some(crate::math::square_to_cosine_hemisphere(r.next_2d())),
            cos_pdf,
            |_| true,
        );
        assert!(good.p_value > 0.01, "{good:?}");
        assert!((good.pdf_integral - 1.0).abs() < 1e-4);
        let bad = chi2_test(
            100_000,
            g,
            1,
            |r| {
                let w = crate::math::square_to_uniform_sphere(r.next_2d());
                Some(Vec3::new(w.x, w.y, w.z.abs()))
            },
            cos_pdf,
            |_| true,
        );
        assert!(bad.p_value < 1e-6, "{bad:?}");
    }
}
