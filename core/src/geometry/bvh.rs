//! One obvhs compressed wide BVH (CWBVH) over every primitive of every shape.

use glam::{Vec2, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::cwbvh::CwBvh;
use obvhs::BvhBuildParams;

use super::{intersect_triangle, Geometry, Interaction, Ray, RayPre, Shape};

/// A primitive: triangle `index` of shape `shape` (or the whole analytic shape).
#[derive(Clone, Copy, Debug)]
struct PrimRef {
    shape: u32,
    index: u32,
    triangle: bool,
}

pub struct Accel {
    bvh: Option<CwBvh>,
    /// In BVH leaf order: `prims[k]` is the primitive the BVH calls `k`.
    prims: Vec<PrimRef>,
    /// Triangle vertices in the same order, packed so that traversal reads them without
    /// indirection (unused entries for analytic shapes).
    verts: Vec<[Vec3; 3]>,
}

impl Accel {
    pub fn build(shapes: &[Shape]) -> Accel {
        let mut prims = Vec::new();
        let mut aabbs = Vec::new();
        for (s, shape) in shapes.iter().enumerate() {
            let triangle = matches!(shape.geometry, Geometry::Mesh(_));
            for i in 0..shape.prim_count() {
                let (lo, hi) = shape.prim_bounds(i);
                prims.push(PrimRef { shape: s as u32, index: i as u32, triangle });
                aabbs.push(Aabb::new(Vec3A::from(lo), Vec3A::from(hi)));
            }
        }
        if prims.is_empty() {
            return Accel { bvh: None, prims, verts: Vec::new() };
        }
        let bvh = build_cwbvh(&aabbs, BvhBuildParams::medium_build(), &mut Default::default());
        let prims: Vec<PrimRef> = bvh.primitive_indices.iter().map(|&k| prims[k as usize]).collect();
        let verts = prims
            .iter()
            .map(|p| match &shapes[p.shape as usize].geometry {
                Geometry::Mesh(m) => m.tri(p.index as usize),
                _ => [Vec3::ZERO; 3],
            })
            .collect();
        Accel { bvh: Some(bvh), prims, verts }
    }

    pub fn prim_count(&self) -> usize {
        self.prims.len()
    }

    fn obvhs_ray(ray: &Ray) -> obvhs::ray::Ray {
        obvhs::ray::Ray::new(Vec3A::from(ray.o), Vec3A::from(ray.d), ray.tmin, ray.tmax)
    }

    /// Intersects the primitive the BVH calls `k`.
    #[inline(always)]
    fn hit(&self, shapes: &[Shape], k: usize, ray: &Ray, pre: &RayPre, tmax: f32) -> Option<(f32, Vec2)> {
        let prim = self.prims[k];
        if prim.triangle {
            let [p0, p1, p2] = self.verts[k];
            intersect_triangle(ray, pre, tmax, p0, p1, p2).map(|(t, _, b1, b2)| (t, Vec2::new(b1, b2)))
        } else {
            shapes[prim.shape as usize].intersect(prim.index as usize, ray, pre, tmax)
        }
    }

    /// The closest hit along `ray`, if any.
    pub fn intersect(&self, shapes: &[Shape], ray: &Ray) -> Option<Interaction> {
        let bvh = self.bvh.as_ref()?;
        let pre = RayPre::new(ray.d);
        let mut best: Option<(usize, Vec2)> = None;
        let mut hit = obvhs::ray::RayHit::none();
        bvh.ray_traverse(Self::obvhs_ray(ray), &mut hit, |r, k| {
            match self.hit(shapes, k, ray, &pre, r.tmax) {
                Some((t, aux)) => {
                    if t < r.tmax {
                        best = Some((k, aux));
                    }
                    t
                }
                None => f32::INFINITY,
            }
        });
        let (k, aux) = best?;
        let prim = self.prims[k];
        Some(shapes[prim.shape as usize].interaction(prim.shape, prim.index as usize, ray, hit.t, aux))
    }

    /// Whether anything blocks `ray` within `[tmin, tmax)`.
    pub fn occluded(&self, shapes: &[Shape], ray: &Ray) -> bool {
        let Some(bvh) = self.bvh.as_ref() else {
            return false;
        };
        let pre = RayPre::new(ray.d);
        !bvh.ray_traverse_miss(Self::obvhs_ray(ray), |r, k| {
            self.hit(shapes, k, ray, &pre, r.tmax).map_or(f32::INFINITY, |(t, _)| t)
        })
    }
}
