//! One obvhs compressed wide BVH (CWBVH) over every primitive of every shape.

use glam::{Vec2, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::cwbvh::CwBvh;
use obvhs::BvhBuildParams;

use super::{intersect_triangle, Geometry, Interaction, Ray, RayPre, Shape};

/// A primitive in BVH leaf order, 8 bytes: for triangles, `index` is the slot in
/// [`Accel::tris`] (which holds the vertices and the triangle's index in its mesh); for curves
/// the segment, for analytic shapes 0.
#[derive(Clone, Copy, Debug)]
struct PrimRef {
    /// Shape index, with `TRIANGLE` set for mesh triangles.
    shape: u32,
    index: u32,
}

const TRIANGLE: u32 = 1 << 31;

/// Primitive count above which the BVH is built with obvhs' very fast settings.
const FAST_BUILD_ABOVE: usize = 1 << 21;

/// A triangle's vertices packed for traversal, and its index in the mesh.
#[derive(Clone, Copy, Debug)]
struct PackedTri {
    v: [Vec3; 3],
    index: u32,
}

pub struct Accel {
    bvh: Option<CwBvh>,
    /// `prims[k]` is the primitive the BVH calls `k`.
    prims: Vec<PrimRef>,
    /// Triangles in BVH leaf order, so that traversal reads vertices without indirection
    /// through the mesh; analytic shapes and curves take no entry.
    tris: Vec<PackedTri>,
}

impl Accel {
    pub fn build(shapes: &[Shape]) -> Accel {
        let count: usize = shapes.iter().map(|s| s.prim_count()).sum();
        let mut prims = Vec::with_capacity(count);
        let mut aabbs = Vec::with_capacity(count);
        for (s, shape) in shapes.iter().enumerate() {
            let kind = if matches!(shape.geometry, Geometry::Mesh(_)) { TRIANGLE } else { 0 };
            for i in 0..shape.prim_count() {
                let (lo, hi) = shape.prim_bounds(i);
                prims.push(PrimRef { shape: s as u32 | kind, index: i as u32 });
                aabbs.push(Aabb::new(Vec3A::from(lo), Vec3A::from(hi)));
            }
        }
        if prims.is_empty() {
            return Accel { bvh: None, prims, tris: Vec::new() };
        }
        // Past two million primitives (a quarter of a million fibres), obvhs' better builds
        // cost more time than they save: a million fibres (8M segments) load in 7.1 s on 2
        // cores with the very fast build against 8.3 to 9.9 s with the fast one (medium: more),
        // and that fur even renders faster with it (0.063 to 0.081 against 0.047 to 0.054
        // Msamples/s at 8 spp; docs/BENCHMARKS.md).
        let params = if count > FAST_BUILD_ABOVE {
            BvhBuildParams::very_fast_build()
        } else {
            BvhBuildParams::medium_build()
        };
        let mut bvh = build_cwbvh(&aabbs, params, &mut Default::default());
        drop(aabbs);
        let mut tris = Vec::new();
        let prims: Vec<PrimRef> = bvh
            .primitive_indices
            .iter()
            .map(|&k| {
                let mut p = prims[k as usize];
                if p.shape & TRIANGLE != 0 {
                    if let Geometry::Mesh(m) = &shapes[(p.shape & !TRIANGLE) as usize].geometry {
                        tris.push(PackedTri { v: m.tri(p.index as usize), index: p.index });
                        p.index = tris.len() as u32 - 1;
                    }
                }
                p
            })
            .collect();
        tris.shrink_to_fit();
        // Traversal names primitives by leaf order, which `prims` follows: the BVH's own map
        // back to input order is not needed, and the builder leaves its node array at the
        // capacity of one node per primitive (80 bytes each, ten times what is used).
        bvh.primitive_indices = Vec::new();
        bvh.nodes.shrink_to_fit();
        tracing::debug!(
            primitives = prims.len(),
            nodes = bvh.nodes.len(),
            bytes = std::mem::size_of_val(bvh.nodes.as_slice())
                + std::mem::size_of_val(prims.as_slice())
                + std::mem::size_of_val(tris.as_slice()),
            "BVH built"
        );
        Accel { bvh: Some(bvh), prims, tris }
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
        if prim.shape & TRIANGLE != 0 {
            let [p0, p1, p2] = self.tris[prim.index as usize].v;
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
        let shape = prim.shape & !TRIANGLE;
        let index =
            if prim.shape & TRIANGLE != 0 { self.tris[prim.index as usize].index } else { prim.index };
        Some(shapes[shape as usize].interaction(shape, index as usize, ray, hit.t, aux))
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
