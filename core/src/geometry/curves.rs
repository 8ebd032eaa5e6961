//! Round fibres: Mitsuba's `linearcurve` — control points `x y z radius`, consecutive points
//! joined by a frustum whose radius varies linearly, with a sphere at every joint; the two
//! ends of a curve are open (no cap), as Mitsuba's curves are. Each segment is one BVH
//! primitive, so boxes stay tight.
//!
//! Intersection is exact for that shape and computed in f64 relative to the segment's start:
//! fibres are about a thousand times thinner than the distances to them, and f32 would lose
//! the radial term to cancellation. A hit counts only where it lies on the surface of the
//! union of the pieces: front-facing, and not inside a neighbouring frustum or joint sphere.
//! So, as in Mitsuba, a ray leaving a fibre, even through its body, does not hit the fibre it
//! starts in; where rounding puts its origin on the wrong side of the surface it could hit
//! the piece it leaves right there, so the tree does not test that piece for it
//! ([`crate::geometry::Leaving`], inside instances too).

use glam::{DVec3, Vec2, Vec3, Vec4};

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

/// Bytes of a curve file that [`read_curve_file`] reads and parses at a time.
pub const CURVE_BLOCK: usize = 1 << 26;

/// Reads and parses a curve file a block of about [`CURVE_BLOCK`] bytes at a time, each cut
/// just after a blank line, so that the file's text is never held whole (a 66M-segment file
/// is 1.1 GB): at most a block and the part of a curve that runs past it. The result is
/// that of [`parse_curve_file`] on the whole text, errors and their line numbers included.
pub fn read_curve_file(
    reader: impl std::io::Read,
    min_points: usize,
) -> Result<Vec<Vec<(Vec3, f32)>>, CurveError> {
    read_curve_blocks(reader, min_points, CURVE_BLOCK)
}

fn read_curve_blocks(
    mut reader: impl std::io::Read,
    min_points: usize,
    block: usize,
) -> Result<Vec<Vec<(Vec3, f32)>>, CurveError> {
    use std::io::Read;
    let mut curves = Vec::new();
    let mut buf: Vec<u8> = Vec::new();
    let mut line = 1;
    loop {
        // Fill to a block; a curve longer than one makes the buffer grow.
        let room = block.saturating_sub(buf.len()).max(block / 4).max(1);
        let n = (&mut reader).take(room as u64).read_to_end(&mut buf)?;
        let eof = n < room;
        // Cut just after the last blank line ("\n\n" or "\n\r\n"), or take all at the end.
        let cut = if eof {
            buf.len()
        } else {
            let blank = buf.windows(2).rposition(|w| w == b"\n\n").map(|k| k + 2);
            let blank_crlf = buf.windows(3).rposition(|w| w == b"\n\r\n").map(|k| k + 3);
            match blank.max(blank_crlf) {
                Some(cut) => cut,
                None => continue,
            }
        };
        let text = std::str::from_utf8(&buf[..cut]).map_err(|e| {
            let at = line + buf[..e.valid_up_to()].iter().filter(|&&c| c == b'\n').count();
            CurveError::Io(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("line {at}: not UTF-8 text"),
            ))
        })?;
        curves.extend(parse_curve_text(text, line, min_points)?);
        line += text.bytes().filter(|&c| c == b'\n').count();
        buf.drain(..cut);
        if eof {
            break;
        }
    }
    if curves.is_empty() {
        return Err(CurveError::Empty);
    }
    Ok(curves)
}

/// Parses Mitsuba's curve text format: one control point per line, a blank line between
/// curves, no comments. Returns the curves' control points (position, radius). Large files
/// are cut at blank lines into pieces parsed in parallel; errors name the file's line.
pub fn parse_curve_file(text: &str, min_points: usize) -> Result<Vec<Vec<(Vec3, f32)>>, CurveError> {
    let curves = parse_curve_text(text, 1, min_points)?;
    if curves.is_empty() {
        return Err(CurveError::Empty);
    }
    Ok(curves)
}

/// [`parse_curve_file`] of text whose first line is line `first_line` of its file, which
/// may hold no curve.
fn parse_curve_text(
    text: &str,
    first_line: usize,
    min_points: usize,
) -> Result<Vec<Vec<(Vec3, f32)>>, CurveError> {
    use rayon::prelude::*;
    const PIECE: usize = 1 << 20;
    // Piece boundaries: just after a blank line, about every PIECE bytes.
    let bytes = text.as_bytes();
    let mut cuts = vec![0usize];
    let mut at = PIECE;
    while at < bytes.len() {
        // Bytes, not `str` slicing: `at` may fall inside a multi-byte character.
        match bytes[at..].windows(2).position(|w| w == b"\n\n") {
            Some(k) => {
                let cut = at + k + 2;
                cuts.push(cut);
                at = cut + PIECE;
            }
            None => break,
        }
    }
    cuts.push(bytes.len());
    // First line number of each piece.
    let pieces: Vec<(usize, &str)> = {
        let mut line = first_line;
        cuts.windows(2)
            .map(|w| {
                let piece = &text[w[0]..w[1]];
                let first = line;
                line += piece.bytes().filter(|&c| c == b'\n').count();
                (first, piece)
            })
            .collect()
    };
    let parsed: Vec<Vec<Vec<(Vec3, f32)>>> = pieces
        .par_iter()
        .map(|&(first, piece)| parse_piece(piece, first, min_points))
        .collect::<Result<_, _>>()?;
    Ok(parsed.into_iter().flatten().collect())
}

/// Parses whole curves from `text`, whose first line is line `first` of the file.
fn parse_piece(text: &str, first: usize, min_points: usize) -> Result<Vec<Vec<(Vec3, f32)>>, CurveError> {
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
    let mut last = first;
    for (k, raw) in text.lines().enumerate() {
        let line = first + k;
        last = line;
        let t = raw.trim();
        if t.is_empty() {
            finish(&mut current, line, &mut curves)?;
            continue;
        }
        let mut v = [0.0f32; 4];
        let mut n = 0;
        for word in t.split_ascii_whitespace() {
            let x = word.parse::<f32>().ok().filter(|x| x.is_finite());
            match (n < 4, x) {
                (true, Some(x)) => v[n] = x,
                _ => return Err(CurveError::Parse { line, text: t.to_string() }),
            }
            n += 1;
        }
        if n != 4 {
            return Err(CurveError::Parse { line, text: t.to_string() });
        }
        if !(v[3] > 0.0) {
            return Err(CurveError::Radius { line });
        }
        current.push((Vec3::new(v[0], v[1], v[2]), v[3]));
    }
    finish(&mut current, last, &mut curves)?;
    Ok(curves)
}

impl Curves {
    /// Linear curves through the control points (already in world space).
    pub fn linear(curves: &[Vec<(Vec3, f32)>]) -> Curves {
        let mut segments = Vec::with_capacity(curves.iter().map(|c| c.len() - 1).sum());
        for c in curves {
            segments.extend(polyline(c));
        }
        Curves { segments, curve_count: curves.len() }
    }

    /// Uniform cubic B-splines (Mitsuba's `bsplinecurve`), tessellated into `steps` round
    /// segments per span; the spline does not pass through its control points. Returns the
    /// curves and the largest distance between a segment and the spline it replaces (measured
    /// at each segment's midpoint, where the chord is farthest from the arc).
    pub fn bspline(curves: &[Vec<(Vec3, f32)>], steps: usize) -> (Curves, f32) {
        use rayon::prelude::*;
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
        // Tessellated points of one curve, and its largest chord error.
        let tessellate = |c: &Vec<(Vec3, f32)>| -> (Vec<(Vec3, f32)>, f32) {
            let spans = c.len() - 3;
            let mut pts = Vec::with_capacity(spans * steps + 1);
            let mut err = 0.0f32;
            for i in 0..spans {
                for j in 0..steps {
                    let a = eval(c, i, j as f32 / steps as f32);
                    let b = eval(c, i, (j + 1) as f32 / steps as f32).0;
                    let mid = eval(c, i, (j as f32 + 0.5) / steps as f32).0;
                    err = err.max((mid - (a.0 + b) * 0.5).length());
                    pts.push(a);
                }
            }
            pts.push(eval(c, spans - 1, 1.0));
            (pts, err)
        };
        // In chunks of curves, so that parallel work stays coarse, each writing its segments
        // straight into its part of the one array (66M segments are 2.6 GB: built in pieces
        // and then joined, they were held twice).
        const CHUNK: usize = 4096;
        let counts: Vec<usize> =
            curves.chunks(CHUNK).map(|chunk| chunk.iter().map(|c| (c.len() - 3) * steps).sum()).collect();
        let zero = Segment { p0: Vec3::ZERO, p1: Vec3::ZERO, r0: 0.0, r1: 0.0, u0: 0.0, du: 0.0 };
        let mut segments = vec![zero; counts.iter().sum()];
        let mut parts: Vec<&mut [Segment]> = Vec::with_capacity(counts.len());
        let mut rest = segments.as_mut_slice();
        for &n in &counts {
            let (part, tail) = rest.split_at_mut(n);
            parts.push(part);
            rest = tail;
        }
        let max_err = curves
            .par_chunks(CHUNK)
            .zip(parts.into_par_iter())
            .map(|(chunk, out)| {
                let mut max_err = 0.0f32;
                let mut at = 0;
                for c in chunk {
                    let (pts, err) = tessellate(c);
                    max_err = max_err.max(err);
                    for seg in polyline(&pts) {
                        out[at] = seg;
                        at += 1;
                    }
                }
                max_err
            })
            .reduce(|| 0.0f32, f32::max);
        (Curves { segments, curve_count: curves.len() }, max_err)
    }

    pub fn bounds(&self, i: usize) -> (Vec3, Vec3) {
        let s = &self.segments[i];
        (s.p0.min(s.p1) - Vec3::splat(s.r0.max(s.r1)), s.p0.max(s.p1) + Vec3::splat(s.r0.max(s.r1)))
    }
}

/// The segments joining consecutive points of one curve, with u spread evenly along them.
fn polyline(pts: &[(Vec3, f32)]) -> impl Iterator<Item = Segment> + '_ {
    let n = pts.len() - 1;
    pts.windows(2).enumerate().map(move |(i, w)| {
        let ((p0, r0), (p1, r1)) = (w[0], w[1]);
        Segment { p0, p1, r0, r1, u0: i as f32 / n as f32, du: 1.0 / n as f32 }
    })
}

/// Which part of a segment a hit lies on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Piece {
    Frustum = 0,
    /// The sphere at `p1` joining the segment to the next one (a curve's ends are open, as in
    /// Mitsuba: no cap).
    Joint = 1,
}

impl Piece {
    pub fn from_index(k: u32) -> Piece {
        if k == 1 {
            Piece::Joint
        } else {
            Piece::Frustum
        }
    }
}

/// A hit on a fibre: distance, the position along the segment (0..1) and the piece hit.
#[derive(Clone, Copy, Debug)]
pub struct FibreHit {
    pub t: f32,
    pub s: f32,
    pub piece: Piece,
}

impl FibreHit {
    /// The distance, and what `Shape::interaction` needs back: s and the piece.
    #[inline]
    pub fn t_aux(&self) -> (f32, Vec2) {
        (self.t, Vec2::new(self.s, self.piece as u32 as f32))
    }
}

/// Relative margin for "strictly inside": a point on the surface of two pieces (where a joint
/// sphere meets a frustum) is inside neither.
const INSIDE_TOL: f64 = 1e-6;

impl Segment {
    /// Outward normal of `piece` at surface point `p`.
    pub fn normal(&self, piece: Piece, p: Vec3) -> Vec3 {
        let x = p.as_dvec3() - self.p0.as_dvec3();
        let axis = (self.p1 - self.p0).as_dvec3();
        let len = axis.length();
        let n = if piece == Piece::Joint || len == 0.0 {
            x - axis
        } else {
            let a = axis / len;
            let z = x.dot(a);
            let k = (self.r1 - self.r0) as f64 / len;
            let r = self.r0 as f64 + k * z;
            x - a * z - a * (r * k)
        };
        n.normalize_or_zero().as_vec3()
    }

    /// Whether `x` (relative to `origin`) lies strictly inside the segment's frustum.
    fn inside_frustum(&self, origin: DVec3, x: DVec3) -> bool {
        let axis = (self.p1 - self.p0).as_dvec3();
        let len2 = axis.length_squared();
        if !(len2 > 0.0) {
            return false;
        }
        let v = x - (self.p0.as_dvec3() - origin);
        // The position along the segment, 0 at p0 and 1 at p1 (no square root: see
        // `candidates`).
        let s = v.dot(axis) / len2;
        if !(s > 0.0 && s < 1.0) {
            return false;
        }
        let r = self.r0 as f64 + (self.r1 - self.r0) as f64 * s;
        (v - axis * s).length_squared() < r * r * (1.0 - INSIDE_TOL)
    }

    /// Every front-facing hit on the frustum (if `frustum`) and, if `joint`, the sphere at
    /// `p1`, within (tmin, tmax), computed in f64 relative to `p0`: (t, s, piece), unsorted.
    fn candidates(
        &self,
        o: DVec3,
        d: DVec3,
        tmin: f64,
        tmax: f64,
        frustum: bool,
        joint: bool,
    ) -> ([(f64, f64, Piece); 4], usize) {
        let mut out = [(0.0, 0.0, Piece::Frustum); 4];
        let mut n = 0;
        let mut push = |t: f64, s: f64, normal: DVec3, piece: Piece| {
            if t > tmin && t < tmax && normal.dot(d) < 0.0 {
                out[n] = (t, s, piece);
                n += 1;
            }
        };
        let axis = (self.p1 - self.p0).as_dvec3();
        let len2 = axis.length_squared();
        if frustum && len2 > 0.0 {
            // In terms of s, the position along the segment (0 at p0, 1 at p1), so that the
            // axis needs no normalising: one division where a square root and divisions by
            // the length stood in a chain (this test's latency is its cost).
            let inv = 1.0 / len2;
            let k = (self.r1 - self.r0) as f64;
            let (os, ds) = (o.dot(axis) * inv, d.dot(axis) * inv);
            let (op, dp) = (o - axis * os, d - axis * ds);
            let r0 = self.r0 as f64;
            // |op + t dp|^2 = (r0 + k (os + t ds))^2
            let (ra, rb) = (r0 + k * os, k * ds);
            let qa = dp.length_squared() - rb * rb;
            let qb = 2.0 * (op.dot(dp) - ra * rb);
            let qc = op.length_squared() - ra * ra;
            for t in solve_quadratic(qa, qb, qc) {
                let s = os + t * ds;
                if (0.0..=1.0).contains(&s) && r0 + k * s > 0.0 {
                    let x = o + d * t;
                    // The outward normal: off the axis, tilted back by the taper.
                    push(t, s, x - axis * s - axis * ((r0 + k * s) * k * inv), Piece::Frustum);
                }
            }
        }
        if joint {
            let oc = o - axis;
            let r = self.r1 as f64;
            for t in solve_quadratic(d.length_squared(), 2.0 * oc.dot(d), oc.length_squared() - r * r) {
                push(t, 1.0, oc + d * t, Piece::Joint);
            }
        }
        (out, n)
    }
}

impl Curves {
    /// Whether segment `i` continues into segment `i + 1` (same curve).
    #[inline]
    pub(crate) fn joined_to_next(&self, i: usize) -> bool {
        i + 1 < self.segments.len() && self.segments[i + 1].u0 > 0.0
    }

    /// Closest hit on segment `i` within (tmin, tmax) that lies on the surface of the fibre:
    /// front-facing, and not inside another piece of the fibre (the segment's own frustum or
    /// joint spheres, or the neighbouring segments that overlap it). So a ray that starts
    /// inside a fibre, as one leaving it through its body does, never hits that fibre from
    /// within; and a ray from outside sees the union of the pieces.
    #[inline]
    pub fn intersect(&self, i: usize, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> Option<FibreHit> {
        if self.segments[i].missed_by(o, d) {
            return None;
        }
        self.intersect_exact(i, o, d, tmin, tmax, None)
    }

    /// [`Curves::intersect`] without the quick f32 rejection (for segments that passed it).
    ///
    /// `leaving`: the piece of this segment that the ray leaves, when it was spawned from a
    /// hit on it; that piece is not tested. Each piece is convex (a frustum, a sphere of
    /// radius r) and the ray starts within its offset d of the point it leaves, on either
    /// side of the surface as rounding has it: a line from there meets a convex piece's
    /// surface front-facing only within about sqrt(2 r d) of that point (a ray from inside
    /// only leaves it, back-facing). So the piece can give such a ray nothing but a hit on
    /// itself where it starts (a self-intersection); the segment's other piece is tested as
    /// usual (a ray leaving a frustum can meet its joint sphere where the fibre bends).
    pub(crate) fn intersect_exact(
        &self,
        i: usize,
        o: Vec3,
        d: Vec3,
        tmin: f32,
        tmax: f32,
        leaving: Option<Piece>,
    ) -> Option<FibreHit> {
        let seg = &self.segments[i];
        let origin = seg.p0.as_dvec3();
        let (o, d) = (o.as_dvec3() - origin, d.as_dvec3());
        let frustum = leaving != Some(Piece::Frustum);
        let joint = leaving != Some(Piece::Joint) && self.joined_to_next(i);
        let (mut cands, n) = seg.candidates(o, d, tmin as f64, tmax as f64, frustum, joint);
        let cands = &mut cands[..n];
        cands.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        cands
            .iter()
            .find(|&&(t, _, piece)| !self.covered(i, piece, origin, o + d * t))
            .map(|&(t, s, piece)| FibreHit { t: t as f32, s: s as f32, piece })
    }

    /// Whether `x` (relative to `origin`), a point on `piece` of segment `i`, lies strictly
    /// inside another piece of the same fibre. Neighbours are walked while they can reach `x`:
    /// up to the sum of the radii along the curve (one segment each way for thin fibres).
    fn covered(&self, i: usize, piece: Piece, origin: DVec3, x: DVec3) -> bool {
        let seg = &self.segments[i];
        let ball = |c: Vec3, r: f32| {
            (x - (c.as_dvec3() - origin)).length_squared() < (r as f64).powi(2) * (1.0 - INSIDE_TOL)
        };
        if (piece == Piece::Joint && seg.inside_frustum(origin, x))
            || (seg.u0 > 0.0 && ball(seg.p0, seg.r0))
            || (piece == Piece::Frustum && self.joined_to_next(i) && ball(seg.p1, seg.r1))
        {
            return true;
        }
        let reach = seg.r0.max(seg.r1);
        let rel = |p: Vec3| x - (p.as_dvec3() - origin);
        // Backwards, then forwards, while joined. Each step's own joint sphere is the one on
        // the walk's side (p0 backwards, p1 forwards); at the curve's end, a joint sphere poking
        // out of the open end is cut off by the end plane.
        for forward in [false, true] {
            let (mut j, mut dist) = (i, 0.0f32);
            loop {
                let s = &self.segments[j];
                let (joint, r, ends) =
                    if forward { (s.p1, s.r1, !self.joined_to_next(j)) } else { (s.p0, s.r0, s.u0 == 0.0) };
                if j != i {
                    if dist > reach + s.r0.max(s.r1) {
                        break;
                    }
                    if s.inside_frustum(origin, x) || (!ends && ball(joint, r)) {
                        return true;
                    }
                    dist += (s.p1 - s.p0).length();
                }
                if ends {
                    let outward = rel(joint).dot((s.p1 - s.p0).as_dvec3());
                    if piece == Piece::Joint && (if forward { outward > 0.0 } else { outward < 0.0 }) {
                        return true;
                    }
                    break;
                }
                j = if forward { j + 1 } else { j - 1 };
            }
        }
        false
    }
}

impl Segment {
    /// Whether the line `o + t d` (any t) certainly passes farther from the segment's axis
    /// than its larger radius ([`missed_by4`] for this segment alone).
    #[inline]
    pub fn missed_by(&self, o: Vec3, d: Vec3) -> bool {
        missed_by4(o, d, &Segments4::gather([self; 4])) & 1 != 0
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

/// Four segments' axes and larger radii, one segment a lane, for [`missed_by4`].
pub struct Segments4 {
    p0: [Vec4; 3],
    v: [Vec4; 3],
    r: Vec4,
}

impl Segments4 {
    /// The four segments' axes (`v` is `p1 - p0`) and larger radii, read from the segments
    /// themselves: a BVH's fibre leaves keep no copy of them (32 bytes a segment would be half
    /// again what the fur's memory budget allows).
    #[inline(always)]
    pub fn gather(segs: [&Segment; 4]) -> Segments4 {
        let lanes = |f: fn(&Segment) -> f32| Vec4::new(f(segs[0]), f(segs[1]), f(segs[2]), f(segs[3]));
        let p0 = [lanes(|s| s.p0.x), lanes(|s| s.p0.y), lanes(|s| s.p0.z)];
        let p1 = [lanes(|s| s.p1.x), lanes(|s| s.p1.y), lanes(|s| s.p1.z)];
        Segments4 { p0, v: [p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]], r: lanes(|s| s.r0.max(s.r1)) }
    }
}

/// Which of four segments the line `o + t d` (any t) certainly passes farther from than the
/// segment's larger radius (bit `i` for lane `i`): then neither its frustum nor its joint
/// sphere can be hit. A cheap f32 test, four segments at once, that spares the exact f64 one
/// most of the segments a ray's traversal reaches (dense fur puts many in its way).
///
/// It never rejects a hit. It answers only where the closest approach is well conditioned:
/// the line at least about 6 degrees off the segment's axis (sin^2 > 0.01). Nearer to
/// parallel, the f32 cancellation in `a c - b^2` moves the closest point along a thin segment
/// by more than its radius, so those lanes keep the exact test. Where it answers, the error
/// of the distance is below 2 eps |w| / sin, a fifth of the tolerance `1e-5 scale`. A NaN
/// anywhere keeps the exact test too.
#[inline(always)]
pub fn missed_by4(o: Vec3, d: Vec3, s: &Segments4) -> u32 {
    let dot = |a: &[Vec4; 3], b: &[Vec4; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let ds = [Vec4::splat(d.x), Vec4::splat(d.y), Vec4::splat(d.z)];
    let w = [Vec4::splat(o.x) - s.p0[0], Vec4::splat(o.y) - s.p0[1], Vec4::splat(o.z) - s.p0[2]];
    let v = &s.v;
    let a = Vec4::splat(d.dot(d));
    let (b, c, dw, vw) = (dot(&ds, v), dot(v, v), dot(&ds, &w), dot(v, &w));
    // The segment's parameter of the closest approach, clamped to the segment (a NaN stays
    // NaN); then the ray's parameter closest to that point.
    let denom = a * c - b * b;
    let conditioned = denom.cmpgt(Vec4::splat(1e-2) * a * c);
    let free = (a * vw - b * dw) / denom;
    let sp = Vec4::select(free.is_nan_mask(), free, free.max(Vec4::ZERO).min(Vec4::ONE));
    let t = (b * sp - dw) / a;
    let e = [w[0] + ds[0] * t - v[0] * sp, w[1] + ds[1] * t - v[1] * sp, w[2] + ds[2] * t - v[2] * sp];
    let dist2 = dot(&e, &e);
    let max_abs = |x: &[Vec4; 3]| x[0].abs().max(x[1].abs()).max(x[2].abs());
    let scale = Vec4::splat(o.abs().max_element())
        + max_abs(&s.p0)
        + 2.0 * (max_abs(v) + t.abs() * d.abs().max_element());
    let reach = s.r * 1.001 + scale * 1e-5;
    (!dist2.cmple(reach * reach) & conditioned).bitmask()
}

/// Real roots of a t^2 + b t + c, ascending (numerically stable form), without allocating:
/// the roots that do not exist come back as NaN, which no range test accepts.
fn solve_quadratic(a: f64, b: f64, c: f64) -> [f64; 2] {
    if a.abs() < 1e-300 {
        return [if b.abs() > 1e-300 { -c / b } else { f64::NAN }, f64::NAN];
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return [f64::NAN; 2];
    }
    let q = -0.5 * (b + disc.sqrt().copysign(b));
    let (t0, t1) = (q / a, if q != 0.0 { c / q } else { q / a });
    if t0 <= t1 {
        [t0, t1]
    } else {
        [t1, t0]
    }
}

/// Round segments per B-spline span.
pub(crate) const BSPLINE_STEPS: usize = 8;

/// Scene loading: `linearcurve` and `bsplinecurve` (`filename`: `x y z radius` per line, a
/// blank line between curves; `to_world` moves the points, not the radii, as in Mitsuba). The
/// file is read a block at a time, never whole; what parsing holds follows from its lines,
/// counted first in a streamed pass: each a point (16 bytes, up to twice that in a grown
/// list), and each curve (at least `min` points) a list in two lists of lists (about 96
/// bytes).
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
    to_world: &glam::Mat4,
) -> crate::scene::build::R<super::Geometry> {
    use crate::scene::build::{count_lines, file_size, CURVE_PARSE, CURVE_POINT_PARSE};
    let doc = b.doc;
    let o = doc.obj(i);
    let bspline = o.plugin == "bsplinecurve";
    let rel =
        doc.string(i, "filename")?.ok_or_else(|| b.err(o.pos, format!("{} needs a 'filename'", o.plugin)))?;
    let fpos = doc.pos_of(i, "filename");
    let path = doc.resolve_path(fpos, &rel)?;
    let size = file_size(&path);
    let cannot = |e: std::io::Error| doc.err(fpos, format!("cannot read curve file '{rel}': {e}"));
    let lines = *b.cached(&path, "lines", || count_lines(&path)).map_err(cannot)?;
    let min = if bspline { 4 } else { 2 };
    let text = size.min(2 * CURVE_BLOCK as u64);
    let parse = text.saturating_add(lines.saturating_mul(CURVE_POINT_PARSE + CURVE_PARSE / min));
    b.budget.charge(&format!("curve file '{rel}'"), parse, 0).map_err(|e| b.err(fpos, e))?;
    let read = || {
        let file = std::fs::File::open(&path).map_err(cannot)?;
        read_curve_file(file, min as usize).map_err(|e| b.err(fpos, format!("{} '{rel}': {e}", o.plugin)))
    };
    let curves = b.cached(&path, &format!("curves min={min}"), read)?;
    // The parsed points, in their own space; this scene's copy is placed by to_world.
    let mut curves = std::sync::Arc::try_unwrap(curves).unwrap_or_else(|c| (*c).clone());
    for c in &mut curves {
        for (p, _) in c.iter_mut() {
            *p = to_world.transform_point3(*p);
        }
    }
    b.assets.push(path);
    // A B-spline of n points has n - 3 spans of BSPLINE_STEPS segments; a polyline n - 1
    // segments.
    let segments: u64 = curves
        .iter()
        .map(|c| if bspline { c.len().saturating_sub(3) * BSPLINE_STEPS } else { c.len().saturating_sub(1) } as u64)
        .sum();
    let kept = segments.saturating_mul(std::mem::size_of::<Segment>() as u64);
    // Meanwhile the parsed points are still held, and the B-spline tessellation's points of
    // the curves being worked on (a few thousand per thread).
    let points = parse - text;
    b.budget
        .charge(&format!("curve file '{rel}'"), points.saturating_add(kept), kept)
        .map_err(|e| b.err(fpos, e))?;
    Ok(super::Geometry::Curves(if bspline {
        let (c, err) = Curves::bspline(&curves, BSPLINE_STEPS);
        tracing::debug!("bsplinecurve '{rel}': {} segments, chord error {err:.3e}", c.segments.len());
        c
    } else {
        Curves::linear(&curves)
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One tapered segment as a curve; `s.intersect(o, d, ..)` tests it.
    struct One(Curves);
    impl One {
        fn intersect(&self, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> Option<FibreHit> {
            self.0.intersect(0, o, d, tmin, tmax)
        }
    }

    fn fibre() -> One {
        One(Curves::linear(&[vec![(Vec3::new(0.0, -1.0, 0.0), 0.002), (Vec3::new(0.0, 1.0, 0.0), 0.001)]]))
    }

    /// A ray spawned from a hit on a fibre piece (offset as the integrator offsets it, in
    /// every direction, into the fibre and out of it) gets no real hit from that piece: the
    /// convexity argument of `intersect_exact`'s `leaving`, tested. Without the skip the
    /// piece does give hits, all within rounding of the tangent plane at the point left
    /// (self-intersections: the hit point's error bound leaves out the rounding of t to f32);
    /// otherwise the closest hit is the same with the skip as without. A zigzag of tapered
    /// segments, so that rays leaving one piece meet others (neighbours, joint spheres).
    #[test]
    fn a_ray_leaving_a_fibre_piece_never_hits_it_again() {
        let mut rnd = uniform_numbers(0x9e37_79b9u32);
        let pts: Vec<(Vec3, f32)> = (0..8)
            .map(|k| {
                (
                    Vec3::new(k as f32 * 0.02, if k % 2 == 0 { 0.0 } else { 0.015 }, 0.0),
                    0.004 - 0.0003 * k as f32,
                )
            })
            .collect();
        let c = Curves::linear(&[pts.clone()]);
        let n_seg = c.segments.len();
        let closest = |o: Vec3, d: Vec3, leaving: Option<(usize, Piece)>| {
            (0..n_seg)
                .filter_map(|i| {
                    let skip = leaving.filter(|l| l.0 == i).map(|l| l.1);
                    c.intersect_exact(i, o, d, 0.0, f32::INFINITY, skip).map(|h| (h, i))
                })
                .min_by(|a, b| a.0.t.total_cmp(&b.0.t))
        };
        let (mut leaving_rays, mut self_hits, mut elsewhere) = (0, 0, 0);
        for _ in 0..20_000 {
            // A ray from afar at a point near the fibre.
            let (a, _) = pts[(rnd() * 7.0) as usize];
            let target = a
                + Vec3::new(rnd() * 0.02, rnd() * 0.015, 0.0)
                + (Vec3::new(rnd(), rnd(), rnd()) - 0.5) * 0.01;
            let o =
                target + (Vec3::new(rnd(), rnd(), rnd()) - 0.5).normalize_or(Vec3::Z) * (0.05 + rnd() * 5.0);
            let Some((hit, i)) = closest(o, (target - o).normalize(), None) else { continue };
            let seg = &c.segments[i];
            let d0 = (target - o).normalize();
            let (p, p_err, _) = seg.surface(o, d0, &hit);
            let n = seg.normal(hit.piece, p);
            for _ in 0..4 {
                let w = crate::math::square_to_uniform_sphere(glam::Vec2::new(rnd(), rnd()));
                let ro = crate::math::offset_ray_origin(p, p_err, n, w);
                leaving_rays += 1;
                let full = closest(ro, w, None);
                let skipped = closest(ro, w, Some((i, hit.piece)));
                match full {
                    Some((h, j)) if j == i && h.piece == hit.piece => {
                        // Only where rounding puts the surface: within 1e-6 of the tangent
                        // plane at the point left (a grazing ray may run a little along it).
                        let off = ((ro + w * h.t) - p).dot(n).abs();
                        assert!(
                            off < 1e-6,
                            "a real hit on the piece left: t {} {off} ({:?})",
                            h.t,
                            hit.piece
                        );
                        // With the skip: never that piece, and nothing nearer.
                        assert!(
                            skipped.is_none_or(|(g, j)| !(j == i && g.piece == hit.piece) && g.t >= h.t),
                            "the skip kept the piece left or found a nearer hit: {skipped:?}"
                        );
                        self_hits += 1;
                    }
                    _ => {
                        assert_eq!(full.map(|(h, j)| (h.t, j)), skipped.map(|(h, j)| (h.t, j)));
                        // The segment's other piece, or the fibre's others, still hit.
                        elsewhere += matches!(full, Some((h, j)) if h.t > 1e-4 && (j != i || h.piece != hit.piece))
                            as u32;
                    }
                }
            }
        }
        assert!(leaving_rays > 20_000, "{leaving_rays} rays");
        assert!(elsewhere > 300, "{elsewhere} rays met the fibre elsewhere: the test is too easy");
        assert!(self_hits > 100, "{self_hits} self-hits without the skip: nothing left to show");
        eprintln!("{leaving_rays} rays, {self_hits} self-hits, {elsewhere} hits elsewhere on the fibre");
    }

    /// Numbers in [0, 1] from a 32-bit xorshift seeded with `state`.
    fn uniform_numbers(mut state: u32) -> impl FnMut() -> f32 {
        move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            state as f32 / u32::MAX as f32
        }
    }

    /// The f32 pre-test never rejects a ray that the exact test hits: rays aimed near
    /// tapered, thin and thick segments in every orientation, from near and far, grazing ones
    /// included.
    #[test]
    fn the_quick_miss_test_never_rejects_a_hit() {
        let mut rnd = uniform_numbers(0x1234_5678u32);
        let (mut hits, mut rejected) = (0, 0);
        for round in 0..20_000 {
            let far = [1.0, 30.0, 1e3][round % 3];
            let centre = Vec3::new(rnd(), rnd(), rnd()) * far;
            let axis = (Vec3::new(rnd(), rnd(), rnd()) - 0.5).normalize_or(Vec3::X)
                * [0.01, 1.0, 5.0][round % 5 % 3];
            let r = [1e-3, 0.05, 0.3][round % 7 % 3];
            let c = Curves::linear(&[vec![(centre, r), (centre + axis, r * (0.3 + rnd()))]]);
            let target = centre + axis * rnd() + (Vec3::new(rnd(), rnd(), rnd()) - 0.5) * 3.0 * r;
            let o = target + (Vec3::new(rnd(), rnd(), rnd()) - 0.5).normalize_or(Vec3::Y) * far * 2.0 * rnd();
            let d = (target - o).normalize_or(Vec3::Z);
            let hit = c.intersect_exact(0, o, d, 0.0, f32::INFINITY, None);
            let quick = c.segments[0].missed_by(o, d);
            // Lane by lane, the same answer whatever the other lanes hold.
            let other = Curves::linear(&[vec![(o + d, 0.1), (o + d * 2.0, 0.1)]]);
            let (a, b) = (&other.segments[0], &c.segments[0]);
            let lanes = missed_by4(o, d, &Segments4::gather([a, b, a, b]));
            assert_eq!((lanes >> 1 & 1, lanes >> 3 & 1), (quick as u32, quick as u32));
            assert_eq!(lanes & 0b101, 0, "a segment on the ray is never missed");
            hits += hit.is_some() as u32;
            rejected += quick as u32;
            assert!(!(quick && hit.is_some()), "round {round}: rejected a hit at {:?}", hit);
        }
        // The test is meaningful: both outcomes occur often.
        assert!(hits > 2000 && rejected > 2000, "{hits} hits, {rejected} rejected");
    }

    /// Lines nearly parallel to thin segments, where f32 cancellation misplaces the closest
    /// approach: the quick test must leave them to the exact one. The first two are the
    /// review's cases (the line enters the tube near the far end; a hair-scale fibre seen
    /// nearly end-on), the third a ray 1e-8 from the axis at 2e-3 rad; then a sweep of angles
    /// from 1e-5 to 0.3 rad and radii from 1e-6 to 1e-2 of the length.
    #[test]
    fn the_quick_miss_test_leaves_near_parallel_rays_to_the_exact_test() {
        let check = |p0: Vec3, p1: Vec3, r: f32, o: Vec3, d: Vec3| {
            let c = Curves::linear(&[vec![(p0, r), (p1, r)]]);
            let hit = c.intersect_exact(0, o, d, 0.0, f32::INFINITY, None);
            assert!(
                !(hit.is_some() && c.segments[0].missed_by(o, d)),
                "rejected a hit: {p0} {p1} {r} {o} {d}"
            );
            hit.is_some()
        };
        assert!(check(
            Vec3::new(0.0, 0.005, 0.0),
            Vec3::new(10.0, 0.0, 0.0),
            0.001,
            Vec3::new(-1.0, 0.0, 0.0),
            Vec3::X
        ));
        assert!(check(
            Vec3::new(0.0009, 0.0, 0.0),
            Vec3::new(0.0, 0.0, 1.0),
            0.0005,
            Vec3::new(0.0, 0.0, -0.5),
            Vec3::Z
        ));
        check(
            Vec3::new(-0.489_411_9, 0.683_489_7, 0.346_227),
            Vec3::new(0.125_792_5, -0.050_639_8, 0.633_589_9),
            1e-5,
            Vec3::new(-0.055_284_1, 0.165_530_9, 0.548_969_5),
            Vec3::new(0.614_250_8, -0.734_794_7, 0.287_702_2),
        );
        let mut hits = 0;
        for k in 0..4000 {
            let angle = 1e-5 * (3e4f32).powf((k % 100) as f32 / 99.0);
            let r = 1e-6 * (1e4f32).powf((k / 100 % 40) as f32 / 39.0);
            let (p0, p1) = (Vec3::new(0.3, -0.2, 0.1), Vec3::new(1.3, 0.4, -0.5));
            let axis = (p1 - p0).normalize();
            let side = axis.cross(Vec3::Z).normalize();
            let d = (axis * angle.cos() + side * angle.sin()).normalize();
            // Aimed at a point on the axis, offset sideways by up to 1.5 radii.
            let target =
                p0 + (p1 - p0) * ((k % 7) as f32 / 6.0) + side.cross(axis) * r * ((k % 5) as f32 * 0.375);
            hits += check(p0, p1, r, target - d * 2.0, d) as u32;
        }
        assert!(hits > 1000, "{hits} hits: the sweep should mostly hit");
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

    /// Read a block at a time, a file gives what its whole text gives: the same curves for
    /// blocks smaller than a curve, than a line, and larger than the file, with "\n" or
    /// "\r\n" line ends; and errors at the same line.
    #[test]
    fn curve_files_read_in_blocks_parse_as_whole_text() {
        let mut text = String::new();
        for c in 0..300 {
            for k in 0..(2 + c % 5) {
                text += &format!("{} {}.5 {} 0.0{}\n", c, k, c % 7, 1 + k % 9);
            }
            text += if c % 3 == 0 { "\n\n" } else { "\n" };
        }
        let whole = parse_curve_file(&text, 2).unwrap();
        assert_eq!(whole.len(), 300);
        let crlf = text.replace('\n', "\r\n");
        for block in [5, 17, 64, 1000, 1 << 20] {
            for t in [&text, &crlf] {
                let read = read_curve_blocks(t.as_bytes(), 2, block).unwrap();
                assert_eq!(read, whole, "block {block}");
            }
        }
        // An error deep in the file names the same line either way.
        let bad = text.replacen("150 1.5", "150 x", 1);
        let line = |r: Result<Vec<Vec<(Vec3, f32)>>, CurveError>| match r {
            Err(CurveError::Parse { line, .. }) => line,
            other => panic!("{other:?}"),
        };
        let at = line(parse_curve_file(&bad, 2));
        assert!(at > 400, "line {at}");
        for block in [5, 64, 1000] {
            assert_eq!(line(read_curve_blocks(bad.as_bytes(), 2, block)), at, "block {block}");
        }
        assert!(matches!(read_curve_blocks(&b"\n\n\n"[..], 2, 4), Err(CurveError::Empty)));
        assert!(matches!(read_curve_blocks(&b"0 0 0 1\n\xff 0 0 1\n"[..], 2, 4), Err(CurveError::Io(_))));
    }

    #[test]
    fn hits_a_thin_fibre_from_far_away_at_the_right_distance() {
        let s = fibre();
        // Radius at y = 0 is 0.0015: a ray from z = 100 aimed at x = 0.001 hits.
        let o = Vec3::new(0.001, 0.0, 100.0);
        let hit = s.intersect(o, -Vec3::Z, 0.0, f32::INFINITY).unwrap();
        let expect = 100.0 - (0.0015f64 * 0.0015 - 0.001f64 * 0.001).sqrt();
        assert!(((hit.t as f64) - expect).abs() < 1e-5, "{} vs {expect}", hit.t);
        let n = s.0.segments[0].normal(hit.piece, o - Vec3::Z * hit.t);
        assert!(hit.piece == Piece::Frustum && n.z > 0.0 && (n.length() - 1.0).abs() < 1e-5);
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
        // Along the axis (end-on): the end is open, as in Mitsuba, so the ray enters the tube
        // and, seeing only its inside, hits nothing.
        assert!(s.intersect(Vec3::new(0.0, 5.0, 0.0), -Vec3::Y, 0.0, f32::INFINITY).is_none());
        // Grazing the silhouette (edge-on) and parallel to the axis just outside: no NaN.
        for (o, d) in [
            (Vec3::new(0.0015, 0.0, 3.0), -Vec3::Z),
            (Vec3::new(0.0019, -5.0, 0.0), Vec3::Y),
            (Vec3::new(0.0, 0.0, 0.0), Vec3::Y),
        ] {
            if let Some(h) = s.intersect(o, d, 0.0, f32::INFINITY) {
                let n = s.0.segments[0].normal(h.piece, o + d * h.t);
                assert!(h.t.is_finite() && n.is_finite() && h.s.is_finite(), "{o} {d}: {h:?}");
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

#[cfg(test)]
mod union_tests {
    use super::*;
    use crate::math::square_to_uniform_sphere;
    use crate::testing::Pcg;

    /// A wiggly fibre as fat as its segments are long (radius 0.1 to 0.3, segments ~0.2), so
    /// joint spheres reach two segments away, plus a straight fibre.
    fn fibres() -> Curves {
        let wiggly: Vec<(Vec3, f32)> = (0..12)
            .map(|k| {
                let t = k as f32 * 0.2;
                (Vec3::new(t, 0.3 * (2.0 * t).sin(), 0.2 * (3.0 * t).cos()), 0.1 + 0.2 * (k % 3) as f32 / 2.0)
            })
            .collect();
        let straight: Vec<(Vec3, f32)> =
            (0..6).map(|k| (Vec3::new(0.0, 3.0, k as f32 * 0.1), 0.25)).collect();
        Curves::linear(&[wiggly, straight])
    }

    fn closest(c: &Curves, o: Vec3, d: Vec3) -> Option<(f32, usize, FibreHit)> {
        (0..c.segments.len())
            .filter_map(|i| c.intersect(i, o, d, 0.0, f32::INFINITY).map(|h| (h.t, i, h)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
    }

    /// Whether the ray o + t d, t in [0, tmax], enters a curve through one of its open ends.
    fn through_open_end(c: &Curves, o: Vec3, d: Vec3, tmax: f32) -> bool {
        let n = c.segments.len();
        (0..n).any(|i| {
            let s = c.segments[i];
            let mut ends = vec![];
            if s.u0 == 0.0 {
                ends.push((s.p0, s.p0 - s.p1, s.r0));
            }
            if i + 1 == n || c.segments[i + 1].u0 == 0.0 {
                ends.push((s.p1, s.p1 - s.p0, s.r1));
            }
            ends.into_iter().any(|(p, a, r)| {
                let t = (p - o).dot(a) / d.dot(a);
                t > 0.0 && t < tmax && (o + d * t - p).length() < r * 1.001
            })
        })
    }

    /// Strictly inside any piece of any segment, by brute force, with a looser margin.
    fn deep_inside(c: &Curves, x: Vec3, margin: f64) -> bool {
        c.segments.iter().any(|s| {
            let x = x.as_dvec3();
            let ball = |p: Vec3, r: f32| (x - p.as_dvec3()).length() < r as f64 * (1.0 - margin);
            let axis = (s.p1 - s.p0).as_dvec3();
            let len = axis.length();
            let a = axis / len;
            let v = x - s.p0.as_dvec3();
            let z = v.dot(a);
            let r = s.r0 as f64 + (s.r1 - s.r0) as f64 * (z / len);
            let frustum = z > 0.0 && z < len && (v - a * z).length() < r * (1.0 - margin);
            // End caps are open, but their spheres' insides are inside the tube anyway near
            // the joint; only joint spheres are part of the fibre.
            let joint0 = s.u0 > 0.0;
            let joint1 = c.segments.iter().any(|t| t.p0 == s.p1 && t.u0 > 0.0);
            (joint0 && ball(s.p0, s.r0)) || (joint1 && ball(s.p1, s.r1)) || frustum
        })
    }

    /// Rays from outside aimed at points on the axis, and rays from points inside the fibres
    /// in random directions (20,000 of each): every hit lies on the surface of the union (never
    /// inside a piece, margin 1e-4), faces the ray, and a ray aimed at the axis always hits
    /// before reaching it (no holes where pieces meet).
    #[test]
    fn hits_lie_on_the_union_surface_and_never_inside_it() {
        let c = fibres();
        let mut rng = Pcg::new(5);
        let mut inside_hits = 0;
        for k in 0..40_000 {
            let i = (rng.next_f32() * c.segments.len() as f32) as usize % c.segments.len();
            let s = c.segments[i];
            let axis_point = s.p0.lerp(s.p1, rng.next_f32());
            let (o, d, target) = if k % 2 == 0 {
                let o = axis_point + square_to_uniform_sphere(rng.next_2d()) * 3.0;
                (o, (axis_point - o).normalize(), Some((axis_point - o).length()))
            } else {
                // A point inside the union: within 0.999 r of the axis at a random offset.
                let r = s.r0 + (s.r1 - s.r0) * 0.5;
                let o = axis_point + square_to_uniform_sphere(rng.next_2d()) * (r * 0.5 * rng.next_f32());
                (o, square_to_uniform_sphere(rng.next_2d()), None)
            };
            let hit = closest(&c, o, d);
            if let Some(t) = target.filter(|&t| !through_open_end(&c, o, d, t)) {
                let (th, _, _) = hit.unwrap_or_else(|| panic!("ray {k} at the axis missed"));
                assert!(th < t, "ray {k}: hit at {th} beyond the axis at {t}");
            }
            if let Some((t, i, h)) = hit {
                let x = o + d * t;
                assert!(!deep_inside(&c, x, 1e-4), "ray {k}: hit at {x} is inside the fibre");
                assert!(c.segments[i].normal(h.piece, x).dot(d) < 0.0, "ray {k}: back-facing hit");
                if target.is_none() {
                    inside_hits += 1;
                }
            }
        }
        // A ray from inside only hits after leaving the fibre and meeting another part of it
        // (the wiggly one bends back on itself rarely); the straight one never.
        assert!(inside_hits < 2_000, "{inside_hits} of 20000 rays from inside hit");
        let mut rng = Pcg::new(9);
        let straight = c.segments.iter().position(|s| s.p0.y == 3.0).unwrap();
        for _ in 0..5_000 {
            let i = straight + (rng.next_f32() * 5.0) as usize % 5;
            let s = c.segments[i];
            let q = crate::math::square_to_uniform_disk_concentric(rng.next_2d()) * 0.249;
            let o = s.p0.lerp(s.p1, rng.next_f32()) + Vec3::new(q.x, q.y, 0.0);
            let d = square_to_uniform_sphere(rng.next_2d());
            let h = (straight..c.segments.len()).find_map(|i| c.intersect(i, o, d, 0.0, f32::INFINITY));
            assert!(h.is_none(), "a ray from inside the straight fibre hit it: {o} {d} {h:?}");
        }
    }
}
