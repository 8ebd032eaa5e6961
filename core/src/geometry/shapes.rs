//! Shapes: triangle meshes and the analytic sphere and disk, with Mitsuba's parameterisations
//! (sphere uv from the object-space polar angles, disk uv = (r, phi / 2pi)).

use glam::{Mat3, Mat4, Vec2, Vec3};

use super::{intersect_triangle, Interaction, Mesh, Ray, RayPre};
use crate::math::{fast_atan2, gamma, Frame, PI};
use crate::simd::F4;

/// A sphere (`center`, `radius`); `rot` maps world directions to the object frame that defines
/// its uv parameterisation.
#[derive(Clone, Debug)]
pub struct Sphere {
    pub center: Vec3,
    pub radius: f32,
    pub rot: Mat3,
    /// Whether a hit computes its uv and tangents (dp/du, dp/dv, and the shading frame along
    /// dp/du): only where the shape's BSDF or emitter reads them ([`crate::bsdf::Bsdf::reads_surface`],
    /// set by the scene's builder). Otherwise the frame is built around the normal alone,
    /// and uv and the tangents are zero: about 6% of envmap.xml's time, whose four balls read
    /// neither.
    pub tangents: bool,
}

impl Sphere {
    /// Mitsuba's sphere uv of the point with outward world normal `n`: (phi / 2 pi, theta / pi).
    /// Both angles by one four-lane atan2 (`F4::atan2`, `fast_atan2`'s operations): theta as
    /// atan2(sqrt(x^2 + y^2), z) rather than acos(z), which took a libm call a hit (1-2% of
    /// envmap.xml's and thinlens.xml's time) and rounds to 0 within 2.4e-4 rad of the poles.
    #[inline]
    pub fn uv(&self, n: Vec3) -> Vec2 {
        let l = self.rot * n;
        let rxy = (l.x * l.x + l.y * l.y).sqrt();
        let [mut phi, theta, _, _] =
            F4::atan2(F4::new([l.y, rxy, 0.0, 0.0]), F4::new([l.x, l.z, 1.0, 1.0])).to_array();
        if phi < 0.0 {
            phi += 2.0 * PI;
        }
        Vec2::new(phi / (2.0 * PI), theta / PI)
    }
}

/// The unit disk in the object xy-plane, facing +z, placed by an affine `to_world`.
#[derive(Clone, Debug)]
pub struct Disk {
    pub to_world: Mat4,
    pub to_object: Mat4,
    pub normal: Vec3,
    pub area: f32,
}

impl Disk {
    pub fn new(to_world: Mat4) -> Disk {
        let ex = to_world.transform_vector3(Vec3::X);
        let ey = to_world.transform_vector3(Vec3::Y);
        let normal = to_world.inverse().transpose().transform_vector3(Vec3::Z).normalize();
        Disk { to_world, to_object: to_world.inverse(), normal, area: PI * ex.cross(ey).length() }
    }

    /// Mitsuba's disk uv: (r, phi / 2 pi) of object-space point `q`.
    #[inline]
    pub fn uv(q: Vec2) -> Vec2 {
        let mut phi = fast_atan2(q.y, q.x);
        if phi < 0.0 {
            phi += 2.0 * PI;
        }
        Vec2::new(q.length(), phi / (2.0 * PI))
    }

    /// World point of object-space `(x, y, 0)` and its rounding error bound.
    pub fn point(&self, x: f32, y: f32) -> (Vec3, Vec3) {
        let m = &self.to_world;
        let p = m.transform_point3(Vec3::new(x, y, 0.0));
        let (c0, c1, c3) = (m.x_axis, m.y_axis, m.w_axis);
        let err = Vec3::new(
            (c0.x * x).abs() + (c1.x * y).abs() + c3.x.abs(),
            (c0.y * x).abs() + (c1.y * y).abs() + c3.y.abs(),
            (c0.z * x).abs() + (c1.z * y).abs() + c3.z.abs(),
        ) * gamma(3);
        (p, err)
    }
}

#[derive(Clone, Debug)]
pub enum Geometry {
    Mesh(Mesh),
    Sphere(Sphere),
    Disk(Disk),
    /// Round fibres (`linearcurve`); one primitive per segment.
    Curves(super::curves::Curves),
    /// A placed copy of a shape group (Mitsuba's `instance`); traversed by the BVH that
    /// holds the group's own tree.
    Instance(Instance),
}

/// A shape group seen through `to_world` (an affine, invertible transform). The group's shapes
/// and their BVH exist once however many instances there are; an instance is one primitive of
/// the top-level BVH, whose box is the group's box carried to world space.
#[derive(Clone, Debug)]
pub struct Instance {
    /// The group, in the order the scene defines them (see `Accel::build_grouped`).
    pub group: u32,
    pub to_world: Mat4,
    pub to_object: Mat4,
    /// The group's box in world space; `None` for an empty group.
    pub bounds: Option<(Vec3, Vec3)>,
    /// The group's box in its own space.
    pub local_bounds: Option<(Vec3, Vec3)>,
}

/// A world ray carried into an instance's space: unit direction, its length there (`scale`)
/// and how far its origin was moved forward along it (`shift`), so that a distance `t` there
/// is `(t + shift) / scale` in the world.
pub(crate) struct LocalRay {
    pub ray: Ray,
    pub scale: f32,
    pub shift: f32,
}

impl Instance {
    /// The instance of `group`, whose shapes lie within `group_bounds` in the group's space.
    pub fn new(group: u32, to_world: Mat4, group_bounds: Option<(Vec3, Vec3)>) -> Instance {
        let bounds = group_bounds.map(|(lo, hi)| {
            let (mut wlo, mut whi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
            for c in 0..8 {
                let corner = Vec3::new(
                    if c & 1 == 0 { lo.x } else { hi.x },
                    if c & 2 == 0 { lo.y } else { hi.y },
                    if c & 4 == 0 { lo.z } else { hi.z },
                );
                let (p, err) = transform_point_err(&to_world, corner);
                (wlo, whi) = (wlo.min(p - err), whi.max(p + err));
            }
            (wlo, whi)
        });
        Instance { group, to_world, to_object: to_world.inverse(), bounds, local_bounds: group_bounds }
    }

    /// `ray`, with its far end at `tmax`, in the group's space. The origin's rounding error
    /// there is stepped over along the ray (as pbrt-v4 does when it moves rays into object
    /// space), so that a ray leaving a surface of the group does not find it again. A ray
    /// from outside the group's box starts again a box diagonal before it: a triangle's hit
    /// is accepted only beyond an error bound that grows with the distance from the ray's
    /// origin, and an instance squashed along an axis makes that distance huge in the
    /// group's space (a panel scaled by 1e-6 across, seen from 6 units, vanished).
    #[inline]
    pub(crate) fn local_ray(&self, ray: &Ray, tmax: f32) -> LocalRay {
        let (o, err) = transform_point_err(&self.to_object, ray.o);
        let d = self.to_object.transform_vector3(ray.d);
        let scale = d.length();
        let d = d / scale;
        let mut shift = d.abs().dot(err);
        if let Some((lo, hi)) = self.local_bounds {
            // Where the ray enters the box (a lower bound: NaN slabs, of a ray along a face,
            // and slabs it never leaves drop out of the max), less the diagonal and far more
            // than the rounding of the slab distances.
            let at = o + d * shift;
            let (t0, t1) = ((lo - at) / d, (hi - at) / d);
            let enter = t0.min(t1).max_element();
            let start = enter - (hi - lo).length() - enter.abs() * 1e-6;
            if start > 0.0 {
                shift += start;
            }
        }
        let ray = Ray {
            o: o + d * shift,
            d,
            tmin: (ray.tmin * scale - shift).max(0.0),
            tmax: tmax * scale - shift,
        };
        LocalRay { ray, scale, shift }
    }

    /// An interaction found in the group's space, in the world: the point and its error bound,
    /// normals (by the inverse transpose, normalised), tangents and the world distance `t`;
    /// `instance` is this instance's shape index.
    pub(crate) fn to_world(&self, it: &Interaction, t: f32, instance: u32) -> Interaction {
        let (p, err) = transform_point_err(&self.to_world, it.p);
        let lin = abs_linear(&self.to_world);
        let p_err = err + lin * it.p_err * (1.0 + gamma(3));
        let normals = Mat3::from_mat4(self.to_object).transpose();
        let ng = (normals * it.ng).normalize();
        let ns = (normals * it.frame.n).normalize();
        let dpdu = self.to_world.transform_vector3(it.dpdu);
        let dpdv = self.to_world.transform_vector3(it.dpdv);
        Interaction {
            p,
            p_err,
            t,
            ng,
            frame: Frame::from_normal_tangent(ns, dpdu),
            dpdu,
            dpdv,
            instance: Some(instance),
            ..*it
        }
    }
}

/// The matrix of absolute values of `m`'s linear part.
fn abs_linear(m: &Mat4) -> Mat3 {
    let a = Mat3::from_mat4(*m);
    Mat3::from_cols(a.x_axis.abs(), a.y_axis.abs(), a.z_axis.abs())
}

/// `m` applied to point `p`, and a bound on the rounding error of that in f32
/// (gamma(3) (|M| |p| + |t|), pbrt 3rd ed., section 3.9.3).
fn transform_point_err(m: &Mat4, p: Vec3) -> (Vec3, Vec3) {
    let err = (abs_linear(m) * p.abs() + m.w_axis.truncate().abs()) * gamma(3);
    (m.transform_point3(p), err)
}

/// A shape placed in the scene, with its material and (optional) area emitter.
#[derive(Clone, Debug)]
pub struct Shape {
    pub geometry: Geometry,
    pub bsdf: u32,
    pub light: Option<u32>,
    pub flip_normals: bool,
    /// The `id` from the scene file, or the plugin name.
    pub name: String,
}

/// A point on a shape's surface, as sampled for area lights.
#[derive(Clone, Copy, Debug)]
pub struct SurfacePoint {
    pub p: Vec3,
    pub p_err: Vec3,
    pub n: Vec3,
    pub uv: Vec2,
}

impl Geometry {
    pub fn prim_count(&self) -> usize {
        match self {
            Geometry::Mesh(m) => m.tris.len(),
            Geometry::Sphere(_) | Geometry::Disk(_) => 1,
            Geometry::Curves(c) => c.segments.len(),
            Geometry::Instance(i) => i.bounds.is_some() as usize,
        }
    }

    pub fn prim_bounds(&self, prim: usize) -> (Vec3, Vec3) {
        match self {
            Geometry::Mesh(m) => {
                let [a, b, c] = m.tri(prim);
                (a.min(b).min(c), a.max(b).max(c))
            }
            Geometry::Sphere(s) => (s.center - s.radius, s.center + s.radius),
            Geometry::Curves(c) => c.bounds(prim),
            Geometry::Instance(i) => i.bounds.unwrap_or((Vec3::ZERO, Vec3::ZERO)),
            Geometry::Disk(d) => {
                let mut lo = Vec3::splat(f32::INFINITY);
                let mut hi = Vec3::splat(f32::NEG_INFINITY);
                for (x, y) in [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)] {
                    let p = d.to_world.transform_point3(Vec3::new(x, y, 0.0));
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
                (lo, hi)
            }
        }
    }
}

impl Shape {
    pub fn prim_count(&self) -> usize {
        self.geometry.prim_count()
    }

    pub fn prim_bounds(&self, prim: usize) -> (Vec3, Vec3) {
        self.geometry.prim_bounds(prim)
    }

    /// Nearest intersection of primitive `prim` closer than `tmax`: `(t, aux)`, where `aux`
    /// carries what [`Shape::interaction`] needs (barycentrics for triangles).
    #[inline]
    pub fn intersect(&self, prim: usize, ray: &Ray, pre: &RayPre, tmax: f32) -> Option<(f32, Vec2)> {
        match &self.geometry {
            Geometry::Mesh(m) => {
                let [p0, p1, p2] = m.tri(prim);
                intersect_triangle(ray, pre, tmax, p0, p1, p2).map(|(t, _, b1, b2)| (t, Vec2::new(b1, b2)))
            }
            Geometry::Sphere(s) => intersect_sphere(s, ray, tmax).map(|t| (t, Vec2::ZERO)),
            Geometry::Curves(c) => c.intersect(prim, ray.o, ray.d, ray.tmin, tmax).map(|h| h.t_aux()),
            Geometry::Disk(d) => {
                let o = d.to_object.transform_point3(ray.o);
                let dir = d.to_object.transform_vector3(ray.d);
                if dir.z == 0.0 {
                    return None;
                }
                let t = -o.z / dir.z;
                if !(t > ray.tmin && t < tmax) {
                    return None;
                }
                let q = o + dir * t;
                if q.x * q.x + q.y * q.y > 1.0 {
                    return None;
                }
                Some((t, Vec2::new(q.x, q.y)))
            }
            Geometry::Instance(_) => unreachable!("the BVH holding an instance's group traverses it"),
        }
    }

    /// Full surface information for a hit found by [`Shape::intersect`].
    pub fn interaction(&self, shape: u32, prim: usize, ray: &Ray, t: f32, aux: Vec2) -> Interaction {
        let mut piece = None;
        let (p, p_err, mut ng, mut ns, uv, dpdu, dpdv) = match &self.geometry {
            Geometry::Mesh(m) => match m.faces.get(prim) {
                Some(f) => {
                    // A flat-shaded triangle's constants, as computed below for other hits.
                    let (p, p_err, uv) = m.point_uv(prim, aux.x, aux.y);
                    let flip = self.flip_normals;
                    let ng = if flip { -f.ng } else { f.ng };
                    let frame = f.frames[flip as usize];
                    let (dpdu, dpdv) = (f.dpdu, f.dpdv);
                    return Interaction {
                        p,
                        p_err,
                        t,
                        ng,
                        frame,
                        uv,
                        dpdu,
                        dpdv,
                        shape,
                        prim: prim as u32,
                        piece: None,
                        instance: None,
                    };
                }
                None => m.surface(prim, aux.x, aux.y),
            },
            Geometry::Curves(c) => {
                let seg = &c.segments[prim];
                let hit_piece = super::curves::Piece::from_index(aux.y as u32);
                piece = Some(hit_piece);
                let hit = super::curves::FibreHit { t, s: aux.x, piece: hit_piece };
                let (p, p_err, uv) = seg.surface(ray.o, ray.d, &hit);
                let n = seg.normal(hit_piece, p);
                let tangent = seg.tangent();
                (p, p_err, n, n, uv, tangent, n.cross(tangent))
            }
            Geometry::Sphere(s) => {
                let n = (ray.at(t) - s.center).normalize();
                let p = s.center + n * s.radius;
                let p_err = (s.center.abs() + (n * s.radius).abs()) * gamma(6);
                if !s.tangents {
                    // Zero tangents: the frame below is then built around the normal alone.
                    (p, p_err, n, n, Vec2::ZERO, Vec3::ZERO, Vec3::ZERO)
                } else {
                    let l = s.rot * n;
                    let uv = s.uv(n);
                    let dpdu = s.rot.transpose() * Vec3::new(-l.y, l.x, 0.0) * (2.0 * PI * s.radius);
                    // v = theta / pi: dp/dv = pi r (cos theta cos phi, cos theta sin phi, -sin theta).
                    let rxy = (l.x * l.x + l.y * l.y).sqrt();
                    let (cp, sp) = if rxy > 0.0 { (l.x / rxy, l.y / rxy) } else { (1.0, 0.0) };
                    let dpdv = s.rot.transpose() * Vec3::new(l.z * cp, l.z * sp, -rxy) * (PI * s.radius);
                    (p, p_err, n, n, uv, dpdu, dpdv)
                }
            }
            Geometry::Disk(d) => {
                let (p, p_err) = d.point(aux.x, aux.y);
                let uv = Disk::uv(aux);
                let (s, c) = crate::math::sin_cos_2pi(uv.y);
                let dpdu = d.to_world.transform_vector3(Vec3::new(c, s, 0.0));
                let dpdv = d.to_world.transform_vector3(Vec3::new(-aux.y, aux.x, 0.0) * (2.0 * PI));
                (p, p_err, d.normal, d.normal, uv, dpdu, dpdv)
            }
            Geometry::Instance(_) => unreachable!("an instance's hits are its group's shapes'"),
        };
        if self.flip_normals {
            ng = -ng;
            ns = -ns;
        }
        Interaction {
            p,
            p_err,
            t,
            ng,
            frame: Frame::from_normal_tangent(ns, dpdu),
            uv,
            dpdu,
            dpdv,
            shape,
            prim: prim as u32,
            piece,
            instance: None,
        }
    }

    /// Surface area of one primitive (triangle areas for meshes).
    pub fn prim_area(&self, prim: usize) -> f64 {
        match &self.geometry {
            Geometry::Mesh(m) => {
                let [a, b, c] = m.tri(prim);
                0.5 * ((b - a).as_dvec3().cross((c - a).as_dvec3())).length()
            }
            Geometry::Sphere(s) => 4.0 * std::f64::consts::PI * (s.radius as f64).powi(2),
            Geometry::Disk(d) => d.area as f64,
            Geometry::Curves(c) => {
                let s = &c.segments[prim];
                std::f64::consts::PI * (s.r0 + s.r1) as f64 * (s.p1 - s.p0).length() as f64
            }
            Geometry::Instance(_) => 0.0,
        }
    }

    /// A uniformly distributed point on the whole shape, where the shape is sampled whole (a
    /// `rectangle`: the 2-D sample maps straight onto it, keeping its stratification); `None`
    /// where it is sampled primitive by primitive ([`Shape::sample_prim`]).
    #[inline]
    pub fn sample_whole(&self, u: Vec2) -> Option<SurfacePoint> {
        let Geometry::Mesh(m) = &self.geometry else { return None };
        let [o, e1, e2] = m.parallelogram?;
        let n = m.faces.first()?.ng;
        let (a, b) = (e1 * u.x, e2 * u.y);
        let p = o + a + b;
        // Each product and sum rounds once, and each edge was rounded once from the corners.
        let p_err = (o.abs() + a.abs() * 2.0 + b.abs() * 2.0) * gamma(4);
        Some(SurfacePoint { p, p_err, n: if self.flip_normals { -n } else { n }, uv: u })
    }

    /// A uniformly distributed point on primitive `prim` with its (flipped) normal.
    pub fn sample_prim(&self, prim: usize, u: Vec2) -> SurfacePoint {
        let (p, p_err, n, uv) = match &self.geometry {
            Geometry::Mesh(m) => {
                let b = crate::math::square_to_uniform_triangle(u);
                // Emission and its cosine follow the shading normal, as for hits.
                match m.faces.get(prim) {
                    Some(f) => {
                        let (p, p_err, uv) = m.point_uv(prim, b.x, b.y);
                        (p, p_err, f.ng, uv)
                    }
                    None => {
                        let (p, p_err, _ng, ns, uv, _, _) = m.surface(prim, b.x, b.y);
                        (p, p_err, ns, uv)
                    }
                }
            }
            Geometry::Sphere(s) => {
                let n = crate::math::square_to_uniform_sphere(u);
                let p = s.center + n * s.radius;
                (p, (s.center.abs() + (n * s.radius).abs()) * gamma(6), n, s.uv(n))
            }
            Geometry::Disk(d) => {
                let q = crate::math::square_to_uniform_disk_concentric(u);
                let (p, p_err) = d.point(q.x, q.y);
                (p, p_err, d.normal, Disk::uv(q))
            }
            Geometry::Curves(_) => unreachable!("the loader refuses emitters on curves"),
            Geometry::Instance(_) => unreachable!("the loader refuses emitters on instances"),
        };
        SurfacePoint { p, p_err, n: if self.flip_normals { -n } else { n }, uv }
    }
}

/// Ray-sphere intersection with the numerically careful discriminant
/// b^2 - ac = a (r^2 - |f - (b/a) d|^2), f = o - c (pbrt 4th ed., section 6.8.1).
#[inline]
fn intersect_sphere(s: &Sphere, ray: &Ray, tmax: f32) -> Option<f32> {
    let f = ray.o - s.center;
    let a = ray.d.length_squared();
    let b = f.dot(ray.d);
    let c = f.length_squared() - s.radius * s.radius;
    let l = f - ray.d * (b / a);
    let disc = a * (s.radius * s.radius - l.length_squared());
    if disc < 0.0 {
        return None;
    }
    let root = disc.sqrt();
    let q = -(b + root.copysign(b));
    let (mut t0, mut t1) = (q / a, c / q);
    if t0 > t1 {
        std::mem::swap(&mut t0, &mut t1);
    }
    if t0 > ray.tmin && t0 < tmax {
        Some(t0)
    } else if t1 > ray.tmin && t1 < tmax {
        Some(t1)
    } else {
        None
    }
}

// Scene loading: `sphere` and `disk`.
use crate::scene::build::{Builder, R};

/// `sphere`: `center`, `radius`, and a `to_world` that scales uniformly.
pub(crate) fn sphere_from(b: &mut Builder, i: usize, to_world: &Mat4) -> R<super::Geometry> {
    use crate::scene::xml::MAX_COORD;
    let doc = b.doc;
    let center = doc.point(i, "center")?.unwrap_or(Vec3::ZERO);
    let radius = doc.float_or(i, "radius", 1.0)?;
    if !(radius > 0.0 && radius <= MAX_COORD) {
        return Err(b.err(
            doc.pos_of(i, "radius"),
            format!("sphere radius must be > 0 and at most {MAX_COORD:e}, found {radius:e}"),
        ));
    }
    let m = *to_world * Mat4::from_translation(center) * Mat4::from_scale(Vec3::splat(radius));
    let c = m.transform_point3(Vec3::ZERO);
    let axes = [m.x_axis.truncate(), m.y_axis.truncate(), m.z_axis.truncate()];
    let r = axes[0].length();
    if axes.iter().any(|a| (a.length() - r).abs() > 1e-4 * r) {
        return Err(b.err(doc.pos_of(i, "to_world"), "sphere to_world must scale uniformly"));
    }
    let rot = Mat3::from_cols(axes[0] / r, axes[1] / r, axes[2] / r).transpose();
    Ok(super::Geometry::Sphere(Sphere { center: c, radius: r, rot, tangents: true }))
}

/// `disk`: the unit disk placed by `to_world`.
pub(crate) fn disk_from(_: &mut Builder, _: usize, to_world: &Mat4) -> R<super::Geometry> {
    Ok(super::Geometry::Disk(Disk::new(*to_world)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sphere's uv against f64 angles: over the whole sphere, and within 1e-3 rad of the
    /// poles, where acos in f32 (the lookup before) was off by up to 2.4e-4 / pi in v.
    #[test]
    fn sphere_uv_is_the_angles_of_the_normal() {
        let s = Sphere { center: Vec3::ZERO, radius: 2.0, rot: Mat3::from_rotation_x(0.3), tangents: true };
        let mut state = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for i in 0..100_000 {
            let phi = 2.0 * std::f64::consts::PI * next();
            let theta = if i % 2 == 0 { (2.0 * next() - 1.0).acos() } else { 1e-3 * next() };
            let theta = if i % 4 == 1 { std::f64::consts::PI - theta } else { theta };
            let l = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
            let n = s.rot.transpose() * Vec3::new(l[0] as f32, l[1] as f32, l[2] as f32);
            // The angles of the f32 normal itself, in f64.
            let m = s.rot * n;
            let (x, y, z) = (m.x as f64, m.y as f64, m.z as f64);
            let want_u = y.atan2(x).rem_euclid(2.0 * std::f64::consts::PI) / (2.0 * std::f64::consts::PI);
            let want_v = (x * x + y * y).sqrt().atan2(z) / std::f64::consts::PI;
            let uv = s.uv(n);
            let du = (uv.x as f64 - want_u).abs();
            assert!(du.min(1.0 - du) < 2e-6, "u {} against {want_u} at {l:?}", uv.x);
            assert!((uv.y as f64 - want_v).abs() < 2e-6, "v {} against {want_v} at {l:?}", uv.y);
            assert!((0.0..=1.0).contains(&uv.x) && (0.0..=1.0).contains(&uv.y));
        }
    }

    #[test]
    fn sphere_hit_from_outside_and_inside() {
        let s =
            Sphere { center: Vec3::new(0.0, 0.0, -5.0), radius: 1.0, rot: Mat3::IDENTITY, tangents: true };
        let r = Ray::new(Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0));
        assert!((intersect_sphere(&s, &r, f32::INFINITY).unwrap() - 4.0).abs() < 1e-5);
        let r = Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::X);
        assert!((intersect_sphere(&s, &r, f32::INFINITY).unwrap() - 1.0).abs() < 1e-6);
        let r = Ray::new(Vec3::ZERO, Vec3::X);
        assert!(intersect_sphere(&s, &r, f32::INFINITY).is_none());
    }

    /// A flat-shaded mesh's precomputed faces give every hit and light sample the bits that
    /// computing them at the hit gives: rectangles and cubes, placed by rotations, uneven and
    /// mirroring scales, far from the origin, tiny; normals flipped or not.
    #[test]
    fn precomputed_faces_give_the_computed_interactions() {
        use super::super::Mesh;
        let placements = [
            Mat4::IDENTITY,
            Mat4::from_rotation_translation(
                glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 2.0),
                Vec3::new(1e4, -3.0, 7.0),
            ),
            Mat4::from_scale(Vec3::new(-2.0, 0.5, 3.0)),
            Mat4::from_scale_rotation_translation(
                Vec3::new(1e-4, 3e-4, 2e-4),
                glam::Quat::from_rotation_y(0.7),
                Vec3::new(0.1, 0.2, 0.3),
            ),
        ];
        let mut seed = 0x1234_5678u32;
        let mut next = || {
            seed = crate::math::hash_u32(seed);
            (seed >> 8) as f32 / 16_777_216.0
        };
        let mut checked = 0;
        for m in &placements {
            for base in [Mesh::rectangle(), Mesh::cube()] {
                let mut plain = base.clone();
                plain.transform_flat(m);
                let mut faced = plain.clone();
                assert!(faced.precompute_faces() > 0);
                for flip_normals in [false, true] {
                    let shape =
                        |geometry| Shape { geometry, bsdf: 0, light: None, flip_normals, name: "m".into() };
                    let (a, b) = (shape(Geometry::Mesh(plain.clone())), shape(Geometry::Mesh(faced.clone())));
                    for prim in 0..plain.tris.len() {
                        for _ in 0..50 {
                            let (b1, b2) = (next(), next());
                            let (b1, b2) = if b1 + b2 > 1.0 { (1.0 - b1, 1.0 - b2) } else { (b1, b2) };
                            let ray = Ray::new(Vec3::new(next(), next(), next()), Vec3::Z);
                            let aux = Vec2::new(b1, b2);
                            let (x, y) = (
                                a.interaction(3, prim, &ray, 2.5, aux),
                                b.interaction(3, prim, &ray, 2.5, aux),
                            );
                            assert_eq!(format!("{x:?}"), format!("{y:?}"), "placement {m:?} prim {prim}");
                            let u = Vec2::new(next(), next());
                            let (x, y) = (a.sample_prim(prim, u), b.sample_prim(prim, u));
                            assert_eq!(format!("{x:?}"), format!("{y:?}"), "placement {m:?} prim {prim}");
                            checked += 1;
                        }
                    }
                }
            }
        }
        assert_eq!(checked, 4 * 2 * (2 + 12) * 50);
    }

    /// A rectangle sampled whole: its points lie on it within their error bound, with the uv
    /// and the normal that a ray hitting there finds, and equal areas of uv get equal shares of
    /// the samples (uv is affine in the point, so that is uniform over the area).
    #[test]
    fn a_rectangle_sampled_whole_is_uniform_and_agrees_with_its_hits() {
        use super::super::{Accel, Mesh};
        let placements = [
            Mat4::from_scale_rotation_translation(
                Vec3::new(2.0, 0.5, 1.0),
                glam::Quat::from_euler(glam::EulerRot::XYZ, 0.4, 1.0, -0.3),
                Vec3::new(300.0, -2.0, 5.0),
            ),
            Mat4::from_scale(Vec3::new(-1.5, 1.0, 1.0)),
        ];
        for m in placements {
            for flip_normals in [false, true] {
                let mesh = Mesh::placed_rectangle(&m);
                let shape = Shape {
                    geometry: Geometry::Mesh(mesh),
                    bsdf: 0,
                    light: None,
                    flip_normals,
                    name: "r".into(),
                };
                let shapes = [shape];
                let accel = Accel::build(&shapes);
                let mut counts = [0u32; 16];
                let n = 16_000;
                for i in 0..n {
                    let u = Vec2::new(((i % 160) as f32 + 0.5) / 160.0, ((i / 160) as f32 + 0.5) / 100.0);
                    let sp = shapes[0].sample_whole(u).expect("a rectangle is sampled whole");
                    let exact = m.as_dmat4().transform_point3(glam::DVec3::new(
                        2.0 * u.x as f64 - 1.0,
                        2.0 * u.y as f64 - 1.0,
                        0.0,
                    ));
                    let err = (sp.p.as_dvec3() - exact).abs();
                    // The mesh's own corners are rounded too: a few ulps of the coordinates.
                    assert!(err.cmple(sp.p_err.as_dvec3() * 4.0 + 1e-4).all(), "{err:?} > {:?}", sp.p_err);
                    let o = sp.p + sp.n * 0.5;
                    let hit = accel
                        .intersect(&shapes, &Ray::new(o, -sp.n))
                        .expect("the ray comes back to the point");
                    assert!((hit.p - sp.p).length() < 1e-3, "{:?} {:?}", hit.p, sp.p);
                    assert!((hit.uv - sp.uv).abs().max_element() < 1e-4, "{:?} {:?}", hit.uv, sp.uv);
                    assert!((hit.frame.n - sp.n).length() < 1e-5, "{:?} {:?}", hit.frame.n, sp.n);
                    counts[((sp.uv.x * 4.0) as usize).min(3) + 4 * ((sp.uv.y * 4.0) as usize).min(3)] += 1;
                }
                assert!(counts.iter().all(|&c| c as i32 == n / 16), "{counts:?}");
            }
        }
    }

    #[test]
    fn disk_area_follows_its_transform() {
        let d = Disk::new(Mat4::from_scale(Vec3::new(2.0, 3.0, 1.0)));
        assert!((d.area - 6.0 * PI).abs() < 1e-4);
    }
}
