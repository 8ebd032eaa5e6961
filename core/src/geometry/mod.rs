//! Geometry: rays, surface interactions, shapes (triangle meshes, analytic spheres and disks)
//! and the BVH over all of their primitives.

pub mod bvh;
pub mod curves;
pub mod mesh;
pub mod shapes;

use glam::{Vec2, Vec3};

use crate::math::{offset_ray_origin, Frame};

pub use bvh::Accel;
pub use mesh::Mesh;
pub use shapes::{Disk, Geometry, Instance, Shape, Sphere};

/// A ray `o + t d` for `t` in `[tmin, tmax)`. `d` is unit length unless stated otherwise
/// (a shadow ray towards a point: within rounding of the offsets, see
/// [`Interaction::spawn_ray_to`]).
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub o: Vec3,
    pub d: Vec3,
    pub tmin: f32,
    pub tmax: f32,
}

impl Ray {
    pub fn new(o: Vec3, d: Vec3) -> Ray {
        Ray { o, d, tmin: 0.0, tmax: f32::INFINITY }
    }

    pub fn at(&self, t: f32) -> Vec3 {
        self.o + self.d * t
    }
}

/// A ray-surface intersection with everything shading needs.
///
/// Aligned to 16 bytes, 128 long: the compiler writes a record with 16-byte stores where it
/// can, and with the record on a 16-byte boundary those stores start at its fields' own
/// boundaries, so that the integrator's reads of a field right after take their values from
/// the stores in flight (see `math::apart`). PGO build, 2 threads, medians
/// of 5 interleaved, with the hit record made after the miss test: textured +6.1% in all
/// (docs/BENCHMARKS.md, issue 15's seventeenth step); the other scenes within the spread.
#[derive(Clone, Copy, Debug)]
#[repr(align(16))]
pub struct Interaction {
    /// Hit point and its absolute floating-point error bound.
    pub p: Vec3,
    pub p_err: Vec3,
    pub t: f32,
    /// Geometric normal (unit; flipped with `flip_normals`).
    pub ng: Vec3,
    /// Shading frame; `frame.n` is the shading normal.
    pub frame: Frame,
    pub uv: Vec2,
    /// Surface derivatives with respect to uv (for texture footprints).
    pub dpdu: Vec3,
    pub dpdv: Vec3,
    pub shape: u32,
    pub prim: u32,
    /// The piece of the fibre segment hit (`None` for other surfaces): rays spawned here skip
    /// it ([`Interaction::leaving`]).
    pub piece: Option<curves::Piece>,
    /// The instance whose placement of a group this hit is on (its shape index; `None` for a
    /// hit on the scene's own shapes). `shape` and `prim` then name the group's member.
    pub instance: Option<u32>,
}

const _: () = assert!(std::mem::size_of::<Interaction>() == 128, "the hit record is no longer 128 bytes");

/// A fibre piece that a ray leaves: the ray was spawned from a hit on it, and the tree's
/// traversal does not test that piece again (see `Curves::intersect_exact`: all it could give
/// such a ray is a hit on itself where the ray starts).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Leaving {
    pub shape: u32,
    pub segment: u32,
    pub piece: curves::Piece,
    /// The instance that places the piece (its shape index), if it is in a group: the same
    /// piece in another placement is another surface, and is tested.
    pub instance: Option<u32>,
}

/// Offsets of the rays through the neighbouring pixel in x and in y (ray differentials).
#[derive(Clone, Copy, Debug)]
pub struct RayDifferentials {
    pub rx: Ray,
    pub ry: Ray,
}

impl Interaction {
    /// The fibre piece that rays spawned here leave, if this is a hit on one.
    #[inline]
    pub fn leaving(&self) -> Option<Leaving> {
        self.piece.map(|piece| Leaving {
            shape: self.shape,
            segment: self.prim,
            piece,
            instance: self.instance,
        })
    }

    /// The texture footprint at this hit of a ray with differentials `d`: where the offset rays
    /// meet the tangent plane gives dp/dx and dp/dy, and least squares against dp/du and dp/dv
    /// gives the uv derivatives (pbrt 3rd ed., section 10.1.1).
    pub fn tex_coord(&self, d: &RayDifferentials) -> crate::texture::TexCoord {
        let n = self.ng;
        let on_plane = |r: &Ray| -> Option<Vec3> {
            let denom = n.dot(r.d);
            if denom.abs() < 1e-12 {
                return None;
            }
            let t = n.dot(self.p - r.o) / denom;
            t.is_finite().then(|| r.o + r.d * t - self.p)
        };
        let (Some(dpdx), Some(dpdy)) = (on_plane(&d.rx), on_plane(&d.ry)) else {
            return self.uv.into();
        };
        let (a, b, c) = (self.dpdu.dot(self.dpdu), self.dpdu.dot(self.dpdv), self.dpdv.dot(self.dpdv));
        let det = a * c - b * b;
        if !(det.abs() > 1e-20) {
            return self.uv.into();
        }
        let solve = |dp: Vec3| {
            let (pu, pv) = (self.dpdu.dot(dp), self.dpdv.dot(dp));
            Vec2::new((c * pu - b * pv) / det, (a * pv - b * pu) / det)
        };
        let (dx, dy) = (solve(dpdx), solve(dpdy));
        if !(dx.is_finite() && dy.is_finite()) {
            return self.uv.into();
        }
        crate::texture::TexCoord { uv: self.uv, dx, dy }
    }

    /// A ray leaving the surface in direction `d`, its origin offset by the hit point's error
    /// bound so that it does not re-hit the surface it starts on (a fibre's bound can fall
    /// short: rays from fibre hits also skip the piece they leave, [`Interaction::leaving`]).
    pub fn spawn_ray(&self, d: Vec3) -> Ray {
        Ray::new(offset_ray_origin(self.p, self.p_err, self.ng, d), d)
    }

    /// A shadow ray from this surface towards `target` (a point already offset off its own
    /// surface, `dist` from this point: the length its light sample's direction was normalised
    /// by), stopping just short of it. The direction is `target - o` from the offset origin
    /// `o`, scaled by `1 / dist` rather than normalised again: a ray that ends where the old
    /// one did (on the segment from `o` to `target`, 1e-4 short), with a direction within
    /// (offsets) / `dist` of unit length, and no square root between the light sample and the
    /// traversal. (Keeping the sample's own direction from the unoffset point instead let the
    /// ray, shifted by this surface's offset, end past the light's surface when the light is
    /// close to it relative to the scene's coordinates, and hit the light itself.)
    pub fn spawn_ray_to(&self, wi: Vec3, target: Vec3, dist: f32) -> Ray {
        let o = offset_ray_origin(self.p, self.p_err, self.ng, wi);
        if !(dist > 0.0 && dist < f32::INFINITY) {
            let v = target - o;
            let len = v.length();
            return Ray { o, d: v / len, tmin: 0.0, tmax: len * (1.0 - 1e-4) };
        }
        Ray { o, d: (target - o) * (1.0 / dist), tmin: 0.0, tmax: dist * (1.0 - 1e-4) }
    }
}

/// Per-ray constants of the watertight ray-triangle test (Woop, Benthin and Wald 2013):
/// the axis permutation that makes the ray's dominant axis z, and the shear that makes the ray
/// direction (0, 0, 1).
#[derive(Clone, Copy, Debug)]
pub struct RayPre {
    kx: usize,
    ky: usize,
    kz: usize,
    sx: f32,
    sy: f32,
    sz: f32,
}

impl RayPre {
    /// What a query of a tree without triangles holds instead (never read).
    pub const UNUSED: RayPre = RayPre { kx: 0, ky: 1, kz: 2, sx: 0.0, sy: 0.0, sz: 1.0 };

    /// `d`'s constants. The dominant axis kz (a tie goes to the later axis), and kx, ky the
    /// next two in turn, swapped where d's kz coordinate is negative (to keep the winding).
    #[inline(always)]
    pub fn new(d: Vec3) -> RayPre {
        #[cfg(all(target_arch = "x86_64", target_feature = "ssse3", target_feature = "sse4.1"))]
        {
            RayPre::new_shuffled(d)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "ssse3", target_feature = "sse4.1")))]
        {
            RayPre::new_selected(d)
        }
    }

    /// [`RayPre::new`] with d's coordinates chosen in a register's lanes without branches: a
    /// bounce's direction is random, so branches on it mispredict about half the time (they
    /// were a fifth of `Accel::closest`'s own time on textured.xml), and an array indexed by
    /// kx was a memory round trip in every query.
    #[cfg_attr(
        all(target_arch = "x86_64", target_feature = "ssse3", target_feature = "sse4.1"),
        allow(dead_code)
    )]
    fn new_selected(d: Vec3) -> RayPre {
        use glam::{BVec3A, Vec3A, Vec3Swizzles};
        let a = d.abs();
        let (x_top, y_top) = (a.x > a.y && a.x > a.z, !(a.x > a.y) && a.y > a.z);
        let kz = 2 - 2 * x_top as usize - y_top as usize;
        let d = Vec3A::from(d);
        let r = Vec3A::select(BVec3A::splat(x_top), d.yzx(), Vec3A::select(BVec3A::splat(y_top), d.zxy(), d));
        // x and y swapped where dz < 0, to keep the winding.
        let flip = r.z < 0.0;
        let r = Vec3A::select(BVec3A::splat(flip), r.yxz(), r);
        let (k1, k2) = ((kz + 1) % 3, (kz + 2) % 3);
        let (kx, ky) = if flip { (k2, k1) } else { (k1, k2) };
        // -dx / dz, -dy / dz and 1 / dz in one division.
        let s = Vec3A::new(-r.x, -r.y, 1.0) / Vec3A::splat(r.z);
        RayPre { kx, ky, kz, sx: s.x, sy: s.y, sz: s.z }
    }

    /// [`RayPre::new_selected`] bit for bit, the permutation looked up: kz and the sign of
    /// d's kz coordinate index a table of the axes kx, ky and of a byte shuffle (`pshufb`)
    /// that puts d's coordinates in the order kx, ky, kz. About 35 instructions fewer a
    /// query than the selects and the remainders.
    #[cfg(all(target_arch = "x86_64", target_feature = "ssse3", target_feature = "sse4.1"))]
    #[inline(always)]
    fn new_shuffled(d: Vec3) -> RayPre {
        use std::arch::x86_64::*;
        /// (kx, ky) at 2 kz + (d[kz] < 0): the next two axes in turn, swapped where d[kz] < 0.
        const AXES: [[usize; 2]; 6] = [[1, 2], [2, 1], [2, 0], [0, 2], [0, 1], [1, 0]];
        /// The byte shuffles to [d[kx], d[ky], d[kz], d[kz]], AXES' entry by entry.
        #[repr(align(16))]
        struct Shuffles([[u8; 16]; 6]);
        static SHUFFLES: Shuffles = Shuffles({
            let mut b = [[0u8; 16]; 6];
            let mut e = 0;
            while e < 6 {
                let lanes = [AXES[e][0], AXES[e][1], e / 2, e / 2];
                let mut i = 0;
                while i < 16 {
                    b[e][i] = (4 * lanes[i / 4] + i % 4) as u8;
                    i += 1;
                }
                e += 1;
            }
            b
        });
        // (kz as `new_selected` finds it. Shared through a helper, always inlined, the
        // surrounding code came out 0.5% more instructions on cbox.)
        let a = d.abs();
        let (x_top, y_top) = (a.x > a.y && a.x > a.z, !(a.x > a.y) && a.y > a.z);
        let kz = 2 - 2 * x_top as usize - y_top as usize;
        // SAFETY: the build's target has SSSE3 and SSE4.1 (the cfg above); the tables' index
        // is below 6 (kz below 3, the sign bit one bit).
        unsafe {
            let v = _mm_setr_ps(d.x, d.y, d.z, 0.0);
            // (A compare, as `r.z < 0.0` above: false for -0 and NaN.)
            let negative = _mm_movemask_ps(_mm_cmplt_ps(v, _mm_setzero_ps())) as usize;
            let i = 2 * kz + (negative >> kz & 1);
            let [kx, ky] = *AXES.get_unchecked(i);
            let shuffle = _mm_load_si128(SHUFFLES.0.get_unchecked(i).as_ptr() as *const __m128i);
            let r = _mm_castsi128_ps(_mm_shuffle_epi8(_mm_castps_si128(v), shuffle));
            // -dx / dz, -dy / dz and 1 / dz in one division.
            let num = _mm_blend_ps::<0b0100>(_mm_xor_ps(r, _mm_set1_ps(-0.0)), _mm_set1_ps(1.0));
            let s = _mm_div_ps(num, _mm_shuffle_ps::<0b1010_1010>(r, r));
            let mut out = [0.0f32; 4];
            _mm_storeu_ps(out.as_mut_ptr(), s);
            RayPre { kx, ky, kz, sx: out[0], sy: out[1], sz: out[2] }
        }
    }
}

/// Watertight ray-triangle intersection. Returns `(t, b0, b1, b2)` with barycentric weights of
/// `p0`, `p1`, `p2`. Edges shared by two triangles are never both missed, and the hit distance is
/// accepted only beyond its own rounding error bound (pbrt 3rd ed., section 3.9.6).
#[inline(always)]
pub fn intersect_triangle(
    ray: &Ray,
    pre: &RayPre,
    tmax: f32,
    p0: Vec3,
    p1: Vec3,
    p2: Vec3,
) -> Option<(f32, f32, f32, f32)> {
    use crate::math::gamma;
    // Plain arrays: indexing a Vec3 with a runtime axis compiles to a match per access.
    let a = (p0 - ray.o).to_array();
    let b = (p1 - ray.o).to_array();
    let c = (p2 - ray.o).to_array();
    let (kx, ky, kz) = (pre.kx, pre.ky, pre.kz);
    let ax = a[kx] + pre.sx * a[kz];
    let ay = a[ky] + pre.sy * a[kz];
    let bx = b[kx] + pre.sx * b[kz];
    let by = b[ky] + pre.sy * b[kz];
    let cx = c[kx] + pre.sx * c[kz];
    let cy = c[ky] + pre.sy * c[kz];
    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        // Fall back to double precision on an edge, so that the sign is exact.
        u = (cx as f64 * by as f64 - cy as f64 * bx as f64) as f32;
        v = (ax as f64 * cy as f64 - ay as f64 * cx as f64) as f32;
        w = (bx as f64 * ay as f64 - by as f64 * ax as f64) as f32;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let az = pre.sz * a[kz];
    let bz = pre.sz * b[kz];
    let cz = pre.sz * c[kz];
    let t_scaled = u * az + v * bz + w * cz;
    if det < 0.0 && (t_scaled >= ray.tmin * det || t_scaled < tmax * det) {
        return None;
    }
    if det > 0.0 && (t_scaled <= ray.tmin * det || t_scaled > tmax * det) {
        return None;
    }
    let inv_det = 1.0 / det;
    let t = t_scaled * inv_det;
    // Reject hits closer than the error bound of t itself.
    let max_zt = az.abs().max(bz.abs()).max(cz.abs());
    let delta_z = gamma(3) * max_zt;
    let max_xt = ax.abs().max(bx.abs()).max(cx.abs());
    let max_yt = ay.abs().max(by.abs()).max(cy.abs());
    let delta_x = gamma(5) * (max_xt + max_zt);
    let delta_y = gamma(5) * (max_yt + max_zt);
    let delta_e = 2.0 * (gamma(2) * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt);
    let max_e = u.abs().max(v.abs()).max(w.abs());
    let delta_t = 3.0 * (gamma(3) * max_e * max_zt + delta_e * max_zt + delta_z * max_e) * inv_det.abs();
    if t <= delta_t {
        return None;
    }
    Some((t, u * inv_det, v * inv_det, w * inv_det))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shared_edge_is_hit_exactly_once_or_twice_never_missed() {
        // Two triangles sharing the diagonal of the unit square; rays aimed at the diagonal.
        let p = [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        let mut misses = 0;
        for i in 1..1000 {
            let s = i as f32 / 1000.0;
            let o = Vec3::new(s, s, 1.0) + Vec3::new(0.3, -0.2, 0.0);
            let d = (Vec3::new(s, s, 0.0) - o).normalize();
            let ray = Ray::new(o, d);
            let pre = RayPre::new(d);
            let h1 = intersect_triangle(&ray, &pre, f32::INFINITY, p[0], p[1], p[2]);
            let h2 = intersect_triangle(&ray, &pre, f32::INFINITY, p[0], p[2], p[3]);
            if h1.is_none() && h2.is_none() {
                misses += 1;
            }
        }
        assert_eq!(misses, 0);
    }

    /// The shuffled constants are the selected ones, bit for bit: random directions, every
    /// tie between axes, zeros of both signs, infinities and NaN.
    #[test]
    fn ray_constants_shuffled_as_selected() {
        let vals = [0.0f32, -0.0, 0.5, -0.5, 1.0, -1.0, 0.3, -0.7, f32::INFINITY, f32::NAN, 1e-30, -1e-30];
        let mut dirs = Vec::new();
        for &x in &vals {
            for &y in &vals {
                for &z in &vals {
                    dirs.push(Vec3::new(x, y, z));
                }
            }
        }
        let mut h = 12345u32;
        for _ in 0..100_000 {
            let mut u = [0.0f32; 3];
            for u in &mut u {
                h = crate::math::hash_u32(h);
                *u = (h >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0;
            }
            dirs.push(Vec3::from(u).normalize_or_zero());
        }
        let bits = |p: &RayPre| (p.kx, p.ky, p.kz, p.sx.to_bits(), p.sy.to_bits(), p.sz.to_bits());
        for d in dirs {
            let (a, b) = (RayPre::new(d), RayPre::new_selected(d));
            // (NaN's bits may differ in payload only where both are NaN.)
            let same = bits(&a) == bits(&b)
                || ((a.kx, a.ky, a.kz) == (b.kx, b.ky, b.kz)
                    && [(a.sx, b.sx), (a.sy, b.sy), (a.sz, b.sz)]
                        .iter()
                        .all(|(x, y)| x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan())));
            assert!(same, "{d:?}: {a:?} against {b:?}");
        }
    }

    #[test]
    fn degenerate_triangle_is_never_hit() {
        let ray = Ray::new(Vec3::new(0.5, 0.0, 1.0), Vec3::new(0.0, 0.0, -1.0));
        let pre = RayPre::new(ray.d);
        let a = Vec3::new(0.0, 0.0, 0.0);
        let b = Vec3::new(1.0, 0.0, 0.0);
        assert!(intersect_triangle(&ray, &pre, f32::INFINITY, a, b, b).is_none());
        assert!(intersect_triangle(&ray, &pre, f32::INFINITY, a, a, a).is_none());
    }

    #[test]
    fn barycentrics_reconstruct_the_hit_point() {
        let (p0, p1, p2) =
            (Vec3::new(-1.0, -1.0, -2.0), Vec3::new(2.0, -1.0, -2.5), Vec3::new(0.0, 2.0, -3.0));
        let ray = Ray::new(Vec3::ZERO, Vec3::new(0.1, 0.05, -1.0).normalize());
        let pre = RayPre::new(ray.d);
        let (t, b0, b1, b2) = intersect_triangle(&ray, &pre, f32::INFINITY, p0, p1, p2).unwrap();
        let p = p0 * b0 + p1 * b1 + p2 * b2;
        assert!((p - ray.at(t)).length() < 1e-5);
    }
}
