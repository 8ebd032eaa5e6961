//! Round fibres: Mitsuba's `linearcurve` — control points `x y z radius`, consecutive points
//! joined by a frustum whose radius varies linearly, with a sphere at every control point
//! (joints and caps). Each segment is one BVH primitive, so boxes stay tight.
//!
//! Intersection is exact for that shape and computed in f64 relative to the segment's start:
//! fibres are about a thousand times thinner than the distances to them, and f32 would lose
//! the radial term to cancellation. Only front faces count (as in Mitsuba): a ray leaving a
//! fibre, even through it, never hits the fibre it starts in.

use glam::{DVec3, Vec2, Vec3};

/// One segment of a fibre: from `p0` (radius `r0`) to `p1` (radius `r1`).
#[derive(Clone, Copy, Debug)]
pub struct Segment {
    pub p0: Vec3,
    pub p1: Vec3,
    pub r0: f32,
    pub r1: f32,
    /// u of the segment's start along its curve, and the u span of the segment.
    pub u0: f32,
    pub du: f32,
}

#[derive(Clone, Debug, Default)]
pub struct Curves {
    pub segments: Vec<Segment>,
    pub curve_count: usize,
}

/// Why a curve file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum CurveError {
    #[error("cannot read curve file: {0}")]
    Io(#[from] std::io::Error),
    #[error("line {line}: expected four numbers 'x y z radius', found \"{text}\"")]
    Parse { line: usize, text: String },
    #[error("line {line}: radius must be positive and finite")]
    Radius { line: usize },
    #[error("curve ending at line {line} has {points} points; at least {min} are needed")]
    TooShort { line: usize, points: usize, min: usize },
    #[error("the file holds no curve")]
    Empty,
}

/// Parses Mitsuba's curve text format: one control point per line, a blank line between
/// curves, no comments. Returns the curves' control points (position, radius).
pub fn parse_curve_file(text: &str, min_points: usize) -> Result<Vec<Vec<(Vec3, f32)>>, CurveError> {
    let mut curves = Vec::new();
    let mut current: Vec<(Vec3, f32)> = Vec::new();
    let finish = |current: &mut Vec<(Vec3, f32)>, line: usize, curves: &mut Vec<Vec<(Vec3, f32)>>| {
        if current.is_empty() {
            return Ok(());
        }
        if current.len() < min_points {
            return Err(CurveError::TooShort { line, points: current.len(), min: min_points });
        }
        curves.push(std::mem::take(current));
        Ok(())
    };
    let mut last = 0;
    for (k, raw) in text.lines().enumerate() {
        let line = k + 1;
        last = line;
        let t = raw.trim();
        if t.is_empty() {
            finish(&mut current, line, &mut curves)?;
            continue;
        }
        let v: Vec<f32> = t
            .split_whitespace()
            .map(|s| s.parse::<f32>())
            .collect::<Result<_, _>>()
            .map_err(|_| CurveError::Parse { line, text: t.to_string() })?;
        if v.len() != 4 || !v.iter().all(|x| x.is_finite()) {
            return Err(CurveError::Parse { line, text: t.to_string() });
        }
        if !(v[3] > 0.0) {
            return Err(CurveError::Radius { line });
        }
        current.push((Vec3::new(v[0], v[1], v[2]), v[3]));
    }
    finish(&mut current, last, &mut curves)?;
    if curves.is_empty() {
        return Err(CurveError::Empty);
    }
    Ok(curves)
}

impl Curves {
    /// Linear curves through the control points (already in world space).
    pub fn linear(curves: &[Vec<(Vec3, f32)>]) -> Curves {
        let mut segments = Vec::new();
        for c in curves {
            let n = c.len() - 1;
            for i in 0..n {
                let (p0, r0) = c[i];
                let (p1, r1) = c[i + 1];
                segments.push(Segment { p0, p1, r0, r1, u0: i as f32 / n as f32, du: 1.0 / n as f32 });
            }
        }
        Curves { segments, curve_count: curves.len() }
    }

    /// Uniform cubic B-splines (Mitsuba's `bsplinecurve`), tessellated into `steps` round
    /// segments per span; the spline does not pass through its control points. Returns the
    /// curves and the largest distance between a segment and the spline it replaces (measured
    /// at each segment's midpoint, where the chord is farthest from the arc).
    pub fn bspline(curves: &[Vec<(Vec3, f32)>], steps: usize) -> (Curves, f32) {
        let eval = |c: &[(Vec3, f32)], i: usize, t: f32| -> (Vec3, f32) {
            let (t2, t3) = (t * t, t * t * t);
            let w = [
                (1.0 - t).powi(3) / 6.0,
                (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0,
                (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0,
                t3 / 6.0,
            ];
            let mut p = Vec3::ZERO;
            let mut r = 0.0;
            for k in 0..4 {
                p += c[i + k].0 * w[k];
                r += c[i + k].1 * w[k];
            }
            (p, r)
        };
        let mut points = Vec::with_capacity(curves.len());
        let mut max_err = 0.0f32;
        for c in curves {
            let spans = c.len() - 3;
            let mut pts = Vec::with_capacity(spans * steps + 1);
            for i in 0..spans {
                for j in 0..steps {
                    let t = j as f32 / steps as f32;
                    pts.push(eval(c, i, t));
                    let (a, b) = (eval(c, i, t).0, eval(c, i, (j + 1) as f32 / steps as f32).0);
                    let mid = eval(c, i, (j as f32 + 0.5) / steps as f32).0;
                    max_err = max_err.max((mid - (a + b) * 0.5).length());
                }
            }
            pts.push(eval(c, spans - 1, 1.0));
            points.push(pts);
        }
        let mut out = Curves::linear(&points);
        out.curve_count = curves.len();
        (out, max_err)
    }

    pub fn bounds(&self, i: usize) -> (Vec3, Vec3) {
        let s = &self.segments[i];
        (s.p0.min(s.p1) - Vec3::splat(s.r0.max(s.r1)), s.p0.max(s.p1) + Vec3::splat(s.r0.max(s.r1)))
    }
}

/// A hit on a fibre: distance, and the point's position along the segment (0..1) with the
/// outward normal, for the interaction.
#[derive(Clone, Copy, Debug)]
pub struct FibreHit {
    pub t: f32,
    pub s: f32,
    pub n: Vec3,
}

impl Segment {
    /// Outward normal at surface point `p`: of the frustum, or of the nearer end sphere where
    /// `p` lies beyond the frustum's ends.
    pub fn normal_at(&self, p: Vec3) -> Vec3 {
        let p0 = self.p0.as_dvec3();
        let x = p.as_dvec3() - p0;
        let axis = self.p1.as_dvec3() - p0;
        let len = axis.length();
        if len == 0.0 {
            return x.normalize_or_zero().as_vec3();
        }
        let a = axis / len;
        let z = x.dot(a);
        if z <= 0.0 {
            return x.normalize_or_zero().as_vec3();
        }
        if z >= len {
            return (x - axis).normalize_or_zero().as_vec3();
        }
        let k = (self.r1 - self.r0) as f64 / len;
        let r = self.r0 as f64 + k * z;
        let radial = x - a * z;
        // Inside the frustum's slab a joint sphere may be the surface hit: take whichever
        // surface the point is closest to.
        let d_frustum = (radial.length() - r).abs();
        let d0 = (x.length() - self.r0 as f64).abs();
        let d1 = ((x - axis).length() - self.r1 as f64).abs();
        if d0 < d_frustum && d0 <= d1 {
            x.normalize_or_zero().as_vec3()
        } else if d1 < d_frustum {
            (x - axis).normalize_or_zero().as_vec3()
        } else {
            (radial - a * (r * k)).normalize_or_zero().as_vec3()
        }
    }
}

impl Segment {
    /// Closest front-facing hit of the frustum or either end sphere within (tmin, tmax).
    pub fn intersect(&self, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> Option<FibreHit> {
        let p0 = self.p0.as_dvec3();
        let o = o.as_dvec3() - p0;
        let d = d.as_dvec3();
        let axis = self.p1.as_dvec3() - p0;
        let len = axis.length();
        let mut best: Option<(f64, f64, DVec3)> = None;
        let mut consider = |t: f64, s: f64, n: DVec3| {
            if t > tmin as f64 && t < tmax as f64 && n.dot(d) < 0.0 && best.is_none_or(|b| t < b.0) {
                best = Some((t, s, n));
            }
        };
        if len > 0.0 {
            let a = axis / len;
            let k = (self.r1 - self.r0) as f64 / len;
            let (oz, dz) = (o.dot(a), d.dot(a));
            let (op, dp) = (o - a * oz, d - a * dz);
            let r0 = self.r0 as f64;
            // |op + t dp|^2 = (r0 + k (oz + t dz))^2
            let qa = dp.length_squared() - k * k * dz * dz;
            let qb = 2.0 * (op.dot(dp) - k * dz * (r0 + k * oz));
            let qc = op.length_squared() - (r0 + k * oz).powi(2);
            for t in solve_quadratic(qa, qb, qc) {
                let z = oz + t * dz;
                if z >= 0.0 && z <= len && r0 + k * z > 0.0 {
                    let x = o + d * t;
                    let n = (x - a * z - a * ((r0 + k * z) * k)).normalize();
                    consider(t, z / len, n);
                }
            }
        }
        for (c, r, s) in [(DVec3::ZERO, self.r0 as f64, 0.0), (axis, self.r1 as f64, 1.0)] {
            let oc = o - c;
            let qa = d.length_squared();
            let qb = 2.0 * oc.dot(d);
            let qc = oc.length_squared() - r * r;
            for t in solve_quadratic(qa, qb, qc) {
                let n = (oc + d * t) / r;
                consider(t, s, n);
            }
        }
        best.map(|(t, s, n)| FibreHit { t: t as f32, s: s as f32, n: n.as_vec3() })
    }

    /// Point on the surface for a hit, its error bound, and uv (u along the curve).
    pub fn surface(&self, ray_o: Vec3, ray_d: Vec3, hit: &FibreHit) -> (Vec3, Vec3, Vec2) {
        let p = (ray_o.as_dvec3() + ray_d.as_dvec3() * hit.t as f64).as_vec3();
        let err = (p.abs() + Vec3::splat(self.r0.max(self.r1))) * crate::math::gamma(8);
        (p, err, Vec2::new(self.u0 + hit.s * self.du, 0.5))
    }

    pub fn tangent(&self) -> Vec3 {
        (self.p1 - self.p0).normalize_or_zero()
    }
}

/// Real roots of a t^2 + b t + c, ascending (numerically stable form).
fn solve_quadratic(a: f64, b: f64, c: f64) -> Vec<f64> {
    if a.abs() < 1e-300 {
        return if b.abs() > 1e-300 { vec![-c / b] } else { vec![] };
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return vec![];
    }
    let q = -0.5 * (b + disc.sqrt().copysign(b));
    let (mut t0, mut t1) = (q / a, if q != 0.0 { c / q } else { q / a });
    if t0 > t1 {
        std::mem::swap(&mut t0, &mut t1);
    }
    vec![t0, t1]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fibre() -> Segment {
        Segment {
            p0: Vec3::new(0.0, -1.0, 0.0),
            p1: Vec3::new(0.0, 1.0, 0.0),
            r0: 0.002,
            r1: 0.001,
            u0: 0.0,
            du: 1.0,
        }
    }

    #[test]
    fn parses_curves_and_reports_bad_lines() {
        let c = parse_curve_file("0 0 0 0.1\n1 0 0 0.1\n\n0 1 0 0.2\n0 2 0 0.2\n0 3 0 0.1\n", 2).unwrap();
        assert_eq!(c.iter().map(|c| c.len()).collect::<Vec<_>>(), vec![2, 3]);
        assert!(matches!(parse_curve_file("0 0 0 0.1\n1 0 0\n", 2), Err(CurveError::Parse { line: 2, .. })));
        assert!(matches!(
            parse_curve_file("0 0 0 0.1\n\n1 0 0 1\n2 0 0 1\n", 2),
            Err(CurveError::TooShort { .. })
        ));
        assert!(matches!(parse_curve_file("# comment\n", 2), Err(CurveError::Parse { line: 1, .. })));
        assert!(matches!(parse_curve_file("0 0 0 0\n1 0 0 1\n", 2), Err(CurveError::Radius { line: 1 })));
    }

    #[test]
    fn hits_a_thin_fibre_from_far_away_at_the_right_distance() {
        let s = fibre();
        // Radius at y = 0 is 0.0015: a ray from z = 100 aimed at x = 0.001 hits.
        let o = Vec3::new(0.001, 0.0, 100.0);
        let hit = s.intersect(o, -Vec3::Z, 0.0, f32::INFINITY).unwrap();
        let expect = 100.0 - (0.0015f64 * 0.0015 - 0.001f64 * 0.001).sqrt();
        assert!(((hit.t as f64) - expect).abs() < 1e-5, "{} vs {expect}", hit.t);
        assert!(hit.n.z > 0.0 && (hit.n.length() - 1.0).abs() < 1e-5);
        // Just outside the radius: a miss.
        assert!(s.intersect(Vec3::new(0.0016, 0.0, 100.0), -Vec3::Z, 0.0, f32::INFINITY).is_none());
    }

    #[test]
    fn a_ray_leaving_the_fibre_does_not_hit_it_again() {
        let s = fibre();
        let hit = s.intersect(Vec3::new(0.0005, 0.2, 5.0), -Vec3::Z, 0.0, f32::INFINITY).unwrap();
        let p = Vec3::new(0.0005, 0.2, 5.0) - Vec3::Z * hit.t;
        // Through the fibre (transmission) and back out (reflection): no second hit.
        for d in [-Vec3::Z, Vec3::Z, Vec3::new(0.3, 0.1, -0.9).normalize()] {
            assert!(s.intersect(p, d, 0.0, f32::INFINITY).is_none(), "{d}");
        }
    }

    #[test]
    fn end_on_and_edge_on_rays_stay_finite() {
        let s = fibre();
        // Along the axis (end-on): hits the cap sphere at y = 1 + r1.
        let hit = s.intersect(Vec3::new(0.0, 5.0, 0.0), -Vec3::Y, 0.0, f32::INFINITY).unwrap();
        assert!((hit.t - (4.0 - 0.001)).abs() < 1e-5 && hit.n.is_finite());
        // Grazing the silhouette (edge-on) and parallel to the axis just outside: no NaN.
        for (o, d) in [
            (Vec3::new(0.0015, 0.0, 3.0), -Vec3::Z),
            (Vec3::new(0.0019, -5.0, 0.0), Vec3::Y),
            (Vec3::new(0.0, 0.0, 0.0), Vec3::Y),
        ] {
            if let Some(h) = s.intersect(o, d, 0.0, f32::INFINITY) {
                assert!(h.t.is_finite() && h.n.is_finite() && h.s.is_finite(), "{o} {d}: {h:?}");
            }
        }
    }
}

#[cfg(test)]
mod bspline_tests {
    use super::*;

    #[test]
    fn bspline_starts_at_the_spline_not_the_control_point_and_bounds_its_chord_error() {
        // Control points on a unit circle, radius 0.01.
        let pts: Vec<(Vec3, f32)> =
            (0..8).map(|k| (Vec3::new((k as f32 * 0.5).cos(), (k as f32 * 0.5).sin(), 0.0), 0.01)).collect();
        let (c, err) = Curves::bspline(std::slice::from_ref(&pts), 8);
        assert_eq!(c.segments.len(), 5 * 8);
        let start = (pts[0].0 + pts[1].0 * 4.0 + pts[2].0) / 6.0;
        assert!((c.segments[0].p0 - start).length() < 1e-6);
        // Chord error of 8 steps on a curve of curvature ~1 and step ~0.06: ~ step^2 / 8.
        assert!(err > 0.0 && err < 1e-3, "{err}");
        // Consecutive segments share their joints.
        for w in c.segments.windows(2) {
            assert_eq!(w[0].p1, w[1].p0);
        }
    }
}
