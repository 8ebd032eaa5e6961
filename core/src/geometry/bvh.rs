//! One obvhs compressed wide BVH (CWBVH) over every primitive of every shape.

use glam::Vec3A;
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::cwbvh::CwBvh;
use obvhs::BvhBuildParams;

use super::{Interaction, Ray, RayPre, Shape};

/// A primitive: triangle `index` of shape `shape` (or the whole analytic shape).
#[derive(Clone, Copy, Debug)]
struct PrimRef {
    shape: u32,
    index: u32,
}

pub struct Accel {
    bvh: Option<CwBvh>,
    /// In BVH leaf order: `prims[k]` is the primitive the BVH calls `k`.
    prims: Vec<PrimRef>,
}

impl Accel {
    pub fn build(shapes: &[Shape]) -> Accel {
        let mut prims = Vec::new();
        let mut aabbs = Vec::new();
        for (s, shape) in shapes.iter().enumerate() {
            for i in 0..shape.prim_count() {
                let (lo, hi) = shape.prim_bounds(i);
                prims.push(PrimRef {
                    shape: s as u32,
                    index: i as u32,
                });
                aabbs.push(Aabb::new(Vec3A::from(lo), Vec3A::from(hi)));
            }
        }
        if prims.is_empty() {
            return Accel { bvh: None, prims };
        }
        let bvh = build_cwbvh(
            &aabbs,
            BvhBuildParams::medium_build(),
            &mut Default::default(),
        );
        let prims = bvh
            .primitive_indices
            .iter()
            .map(|&k| prims[k as usize])
            .collect();
        Accel {
            bvh: Some(bvh),
            prims,
        }
    }

    pub fn prim_count(&self) -> usize {
        self.prims.len()
    }

    fn obvhs_ray(ray: &Ray) -> obvhs::ray::Ray {
        obvhs::ray::Ray::new(Vec3A::from(ray.o), Vec3A::from(ray.d), ray.tmin, ray.tmax)
    }

    /// The closest hit along `ray`, if any.
    pub fn intersect(&self, shapes: &[Shape], ray: &Ray) -> Option<Interaction> {
        let bvh = self.bvh.as_ref()?;
        let pre = RayPre::new(ray.d);
        let mut best: Option<(usize, glam::Vec2)> = None;
        let mut hit = obvhs::ray::RayHit::none();
        bvh.ray_traverse(Self::obvhs_ray(ray), &mut hit, |r, k| {
            let prim = self.prims[k];
            match shapes[prim.shape as usize].intersect(prim.index as usize, ray, &pre, r.tmax) {
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
        Some(shapes[prim.shape as usize].interaction(
            prim.shape,
            prim.index as usize,
            ray,
            hit.t,
            aux,
        ))
    }

    /// Whether anything blocks `ray` within `[tmin, tmax)`.
    pub fn occluded(&self, shapes: &[Shape], ray: &Ray) -> bool {
        let Some(bvh) = self.bvh.as_ref() else {
            return false;
        };
        let pre = RayPre::new(ray.d);
        !bvh.ray_traverse_miss(Self::obvhs_ray(ray), |r, k| {
            let prim = self.prims[k];
            shapes[prim.shape as usize]
                .intersect(prim.index as usize, ray, &pre, r.tmax)
                .map_or(f32::INFINITY, |(t, _)| t)
        })
    }
}
