//! Furnace's wide BVH. obvhs builds a binary BVH (PLOC, reinsertion, and a SAH collapse of
//! leaves to at most [`LEAF_MAX`] primitives); we collapse that into nodes of eight children
//! whose boxes are quantised to 8 bits a plane and stored as structure of arrays, so that one
//! ray tests all eight at once: with AVX2 where the CPU has it, SSE on any other x86-64, plain
//! code elsewhere ([`Kernel`]).
//! Every kernel computes the same IEEE operations in the same order (no fused multiply-add),
//! so the choice changes speed, never an image. Closest-hit traversal visits children nearest
//! first and skips any whose entry distance is past the closest hit so far; shadow rays stop at
//! the first hit.

use std::cell::Cell;
use std::mem::MaybeUninit;

use glam::{Vec2, Vec3, Vec3A};
use obvhs::aabb::Aabb;
use obvhs::bvh2::builder::build_bvh2;
use obvhs::BvhBuildParams;

use super::curves::{missed_by4, Segment, Segments4};
use super::shapes::Instance;
use super::{intersect_triangle, Geometry, Interaction, Leaving, Ray, RayPre, Shape};

/// A primitive in BVH leaf order, 8 bytes: for triangles, `index` is the slot in
/// [`Accel::tris`] (which holds the vertices and the triangle's index in its mesh); for fibre
/// segments the segment's index in its curves; for analytic shapes 0.
#[derive(Clone, Copy, Debug)]
struct PrimRef {
    /// Shape index, with `TRIANGLE` set for mesh triangles and `CURVE` for fibre segments.
    shape: u32,
    index: u32,
}

const TRIANGLE: u32 = 1 << 31;
const CURVE: u32 = 1 << 30;
/// Set on the first primitive of a leaf whose triangles all lie in one plane ([`coplanar`]):
/// a ray spawned from one of them cannot meet the leaf again, unless it leaves within about
/// [`FLAT`] radians of the plane ([`Accel::spawned_from`]).
const PLANAR: u32 = 1 << 29;
/// The shape index of a [`PrimRef`].
const SHAPE: u32 = !(TRIANGLE | CURVE | PLANAR);

/// What the tree builder takes as one primitive: `len` consecutive primitives of one shape
/// from `first`. That is a piece of up to [`PIECE`] consecutive segments of one fibre in a
/// tree mostly of fibres, and one primitive otherwise.
#[derive(Clone, Copy, Debug)]
struct Unit {
    first: PrimRef,
    len: u32,
}

/// Consecutive segments of one fibre that a tree mostly of fibres builds over as one
/// primitive, and so keeps together in one leaf. A leaf's segments then lie side by side in
/// memory, the builder takes a third of the primitives (hair.xml loads in 0.25 s instead of
/// 0.44), and the tree is smaller (hair.xml: 10,524 nodes instead of 13,389). Measured
/// against leaves of up to four segments of any fibres (docs/BENCHMARKS.md, issue 15's
/// thirtieth step): 3 renders hair.xml 3% and whimsical.xml 9% faster; 4 made whimsical
/// faster still but hair 4% slower; 2 made hair 5% slower (and two pieces of 2 a leaf ran 4%
/// more instructions there).
const PIECE: u32 = 3;
const _: () = assert!(PIECE <= LEAF_MAX, "a leaf holds a whole piece");

/// Primitive count above which the BVH is built with obvhs' very fast settings.
const FAST_BUILD_ABOVE: usize = 1 << 21;

/// Children per node.
const WIDTH: usize = 8;
/// Most primitives in a leaf.
const LEAF_MAX: u32 = 4;
/// A child reference with this bit set is a leaf: `count - 1` in the next three bits, the first
/// primitive (in leaf order) in the low 28.
const LEAF: u32 = 1 << 31;
/// A leaf with this bit set holds only triangles (one block of [`LeafTris`]): x86 kernels test
/// them together.
const TRI_LEAF: u32 = 1 << 30;
const FIRST_BITS: u32 = 28;
/// A leaf's first primitive, and its count less one, in its child reference.
const FIRST: u32 = (1 << FIRST_BITS) - 1;
const COUNT: u32 = 3 << FIRST_BITS;
const _: () = assert!(LEAF_MAX <= 4, "a leaf's count takes two bits, its triangles four lanes");
/// Most primitives one BVH can name.
pub const MAX_PRIMS: usize = 1 << FIRST_BITS;

/// Stack entries kept on the call stack; deeper trees (which only degenerate input makes) use
/// a heap stack.
const INLINE_STACK: usize = 512;

/// Eight child boxes, quantised to 8 bits a plane against the node's own box (as in Ylitie et
/// al. 2017's compressed wide BVH): along axis `a`, child `i`'s lower plane is
/// `origin[a] + planes[2 * a][i] * scale[a]` and its upper `planes[2 * a + 1]`, computed in f32
/// exactly so in traversal and checked at build to enclose the child's box. `scale` is a power
/// of two. Lanes not in `used` hold no child. 112 bytes, 14 a child.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(16))]
struct Node {
    origin: [f32; 3],
    used: u32,
    scale: [f32; 4],
    planes: [[u8; WIDTH]; 6],
    child: [u32; WIDTH],
}

const EMPTY_NODE: Node =
    Node { origin: [0.0; 3], used: 0, scale: [1.0; 4], planes: [[0; WIDTH]; 6], child: [0; WIDTH] };

/// A [`Node`] with its planes decoded to f32, bit for bit as the box tests decode them (the
/// AVX2 test's fused multiply-add included, short of a node spanning about 1e38), for
/// trees whose copy of them costs at most [`FLAT_BYTES`] (the AVX2 kernel then reads these:
/// a box test without the eighteen instructions of decoding, the same boxes, so the same
/// traversal and the same images). 256 bytes, 32 a child.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct FlatNode {
    planes: [[f32; WIDTH]; 6],
    child: [u32; WIDTH],
    used: u32,
}

/// Most bytes of [`FlatNode`]s that a scene's trees hold, all together (a fur ball of 96,000
/// segments takes 3.4 MB); larger scenes keep only the 8-bit planes, whose memory per
/// primitive is what the seed's scale is held to (`tests/scale.rs`).
pub const FLAT_BYTES: usize = 4 << 20;

impl FlatNode {
    fn of(node: &Node) -> FlatNode {
        let planes = std::array::from_fn(|p| {
            let a = p / 2;
            std::array::from_fn(|i| node.origin[a] + node.planes[p][i] as f32 * node.scale[a])
        });
        FlatNode { planes, child: node.child, used: node.used }
    }
}

impl Node {
    /// The node over `boxes` (each child's lower and upper corner).
    fn quantise(boxes: &[(Vec3A, Vec3A)]) -> Node {
        let mut node = EMPTY_NODE;
        let lo = boxes.iter().fold(Vec3A::INFINITY, |m, b| m.min(b.0));
        let hi = boxes.iter().fold(Vec3A::NEG_INFINITY, |m, b| m.max(b.1));
        for a in 0..3 {
            let decode = |origin: f32, scale: f32, q: u32| origin + q as f32 * scale;
            // The smallest power of two whose 255 steps from `lo` reach `hi` in f32.
            let mut scale = f32::MIN_POSITIVE;
            let extent = hi[a] - lo[a];
            if extent > 0.0 {
                scale = 2f32.powi((extent / 255.0).log2().ceil() as i32).max(f32::MIN_POSITIVE);
            }
            while decode(lo[a], scale, 255) < hi[a] {
                scale *= 2.0;
            }
            node.origin[a] = lo[a];
            node.scale[a] = scale;
            for (i, b) in boxes.iter().enumerate() {
                let mut ql = (((b.0[a] - lo[a]) as f64 / scale as f64).floor() as u32).min(255);
                while ql > 0 && decode(lo[a], scale, ql) > b.0[a] {
                    ql -= 1;
                }
                let mut qh = (((b.1[a] - lo[a]) as f64 / scale as f64).ceil() as u32).min(255);
                while qh < 255 && decode(lo[a], scale, qh) < b.1[a] {
                    qh += 1;
                }
                debug_assert!(decode(lo[a], scale, ql) <= b.0[a] && decode(lo[a], scale, qh) >= b.1[a]);
                node.planes[2 * a][i] = ql as u8;
                node.planes[2 * a + 1][i] = qh as u8;
            }
        }
        node.used = (1 << boxes.len()) - 1;
        node
    }
}

/// Triangles in leaf order, packed for traversal: each leaf's triangles (1 to 4) as one block
/// of structure of arrays, `data[9 slot0 + (3 vertex + axis) n + lane]` for a leaf whose `n`
/// triangles take slots `slot0..slot0 + n`, so that a leaf's triangles load into the lanes of
/// one register per coordinate (past its `n` lanes, what follows: three floats of padding end
/// the data); and for each slot the triangle's index in its mesh, with its lane and its leaf's
/// count in the top bits. 40 bytes a triangle.
#[derive(Default)]
struct LeafTris {
    data: Vec<f32>,
    index: Vec<u32>,
}

/// The top bits of a [`LeafTris`] index: lane (bits 28-29), leaf count - 1 (bits 30-31).
const LANE_SHIFT: u32 = 28;
const _: () = assert!(MAX_PRIMS <= 1 << LANE_SHIFT, "a mesh index fits below the lane");

impl LeafTris {
    /// Appends a leaf's triangles (vertices and mesh indices); returns the first one's slot.
    fn push(&mut self, tris: &[([Vec3; 3], u32)]) -> u32 {
        let (n, slot0) = (tris.len(), self.index.len());
        debug_assert!((1..=LEAF_MAX as usize).contains(&n));
        self.data.truncate(9 * slot0); // the padding
        for v in 0..3 {
            for a in 0..3 {
                self.data.extend(tris.iter().map(|(p, _)| p[v][a]));
            }
        }
        self.data.extend([0.0; 3]);
        for (lane, &(_, index)) in tris.iter().enumerate() {
            self.index.push(index | (lane as u32) << LANE_SHIFT | (n as u32 - 1) << (LANE_SHIFT + 2));
        }
        slot0 as u32
    }

    /// The triangle in `slot`: its vertices.
    #[inline(always)]
    fn vertices(&self, slot: usize) -> [Vec3; 3] {
        let e = self.index[slot];
        let (lane, n) = ((e >> LANE_SHIFT & 3) as usize, (e >> (LANE_SHIFT + 2)) as usize + 1);
        let block = &self.data[9 * (slot - lane)..];
        [0, 1, 2].map(|v| Vec3::from_array([0, 1, 2].map(|a| block[(3 * v + a) * n + lane])))
    }

    /// The triangle in `slot`: its index in its mesh.
    #[inline(always)]
    fn mesh_index(&self, slot: usize) -> u32 {
        self.index[slot] & ((1 << LANE_SHIFT) - 1)
    }

    fn bytes(&self) -> usize {
        std::mem::size_of_val(self.data.as_slice()) + std::mem::size_of_val(self.index.as_slice())
    }

    fn shrink_to_fit(&mut self) {
        self.data.shrink_to_fit();
        self.index.shrink_to_fit();
    }
}

/// The instruction set that tests a node's eight boxes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// 8 lanes in one 256-bit register (AVX2, with FMA to decode the quantised planes).
    Avx2,
    /// 8 lanes in two 128-bit registers (every x86-64 CPU).
    Sse,
    /// A loop over the lanes.
    Scalar,
}

impl Kernel {
    /// The fastest kernel this CPU runs.
    pub fn detect() -> Kernel {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                return Kernel::Avx2;
            }
            Kernel::Sse
        }
        #[cfg(not(target_arch = "x86_64"))]
        Kernel::Scalar
    }

    /// Every kernel this CPU can run, fastest first.
    pub fn available() -> Vec<Kernel> {
        [Kernel::Avx2, Kernel::Sse, Kernel::Scalar]
            .into_iter()
            .filter(|&k| match k {
                #[cfg(target_arch = "x86_64")]
                Kernel::Avx2 => std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"),
                #[cfg(target_arch = "x86_64")]
                Kernel::Sse => true,
                Kernel::Scalar => true,
                #[allow(unreachable_patterns)]
                _ => false,
            })
            .collect()
    }

    pub fn name(self) -> &'static str {
        match self {
            Kernel::Avx2 => {
                "8-wide BVH, AVX2+FMA, a leaf's triangles in 4 SSE lanes, a pixel's camera rays 8 at a time"
            }
            Kernel::Sse => "8-wide BVH, SSE, a leaf's triangles in 4 SSE lanes",
            Kernel::Scalar => "8-wide BVH, scalar",
        }
    }
}

pub struct Accel {
    nodes: Vec<Node>,
    /// `nodes` decoded ([`FlatNode`]), where the scene's trees are small enough; else empty.
    flat: Vec<FlatNode>,
    /// `prims[k]` is the primitive that leaves call `k`.
    prims: Vec<PrimRef>,
    /// Triangles in leaf order, so that traversal reads vertices without indirection through
    /// the mesh and tests a leaf's triangles together; analytic shapes and curves take no slot.
    tris: LeafTris,
    /// Stack entries a traversal can need: 7 per level below the root, and one.
    stack_size: usize,
    kernel: Kernel,
    /// Whether any primitive is a fibre segment: leaves pre-test segments only then, so a
    /// scene without fibres pays nothing for it.
    curves: bool,
    /// The trees of the shape groups that instances (primitives of this tree) place; empty
    /// in those trees themselves.
    groups: Vec<Accel>,
    /// The leaf that is the whole tree (the root's only child), if it is one; else 0. A ray
    /// that leaves it ([`SpawnedFrom`]) meets nothing, so its query ends before it starts:
    /// textured.xml's ground, two triangles, under a sky.
    lone: u32,
    /// Whether the tree holds triangles: only their test reads a ray's [`RayPre`], which
    /// queries of a tree without them leave uncomputed (balls, disks and fibres).
    triangles: bool,
}

/// A ray's constants for the box tests.
#[derive(Clone, Copy)]
struct BoxRay {
    o: [f32; 3],
    inv: [f32; 3],
    /// The plane (index into [`Node::planes`]) the ray enters through on each axis, and the
    /// one it leaves through.
    near: [usize; 3],
    far: [usize; 3],
}

impl BoxRay {
    fn new(ray: &Ray) -> BoxRay {
        let o = ray.o.to_array();
        let d = ray.d.to_array();
        // (One division of four lanes, not one of two and one of one.)
        let inv = (glam::Vec3A::ONE / glam::Vec3A::from(ray.d)).to_array();
        // The sign bit, so that -0 (1 / -0 = -inf) enters through the upper plane.
        let near = [0, 1, 2].map(|a| 2 * a + d[a].is_sign_negative() as usize);
        let far = near.map(|p| p ^ 1);
        BoxRay { o, inv, near, far }
    }
}

/// Scales the far distance of every box test, so that rounding in `(plane - o) * inv` never
/// culls a box the ray touches (Ize 2013, "Robust BVH ray traversal": 1 + 2 gamma(3)).
const FAR_SCALE: f32 = 1.0 + 2.0 * crate::math::gamma(3);

/// `a > b ? a : b` and `a < b ? a : b`: what `maxps` and `minps` compute, NaN included (a NaN
/// in `a` gives `b`). A slab the ray runs inside of, exactly on its plane, gives 0 * inf = NaN,
/// and is thereby ignored.
#[inline(always)]
fn max_ps(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}
#[inline(always)]
fn min_ps(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// Which of `node`'s children the ray enters within `[tmin, tmax]` (bit `i` for child `i`),
/// and the distance at which it enters each.
#[inline(always)]
fn test_scalar(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
    let mut tn = [0.0; WIDTH];
    let mut mask = 0;
    for i in 0..WIDTH {
        let mut near = tmin;
        let mut far = tmax;
        for a in 0..3 {
            let plane = |p: usize| node.origin[a] + node.planes[p][i] as f32 * node.scale[a];
            near = max_ps((plane(r.near[a]) - r.o[a]) * r.inv[a], near);
            far = min_ps((plane(r.far[a]) - r.o[a]) * r.inv[a], far);
        }
        tn[i] = near;
        mask |= ((near <= far * FAR_SCALE) as u32) << i;
    }
    (mask & node.used, tn)
}

/// Which of `node`'s children `bundle` may meet (bit `i` for child `i`), and a lower bound
/// of the distance to each along its rays. The children's planes are decoded as the
/// traversal decodes them, then taken relative to the bundle's origin (one rounding, within
/// 2^-24 of the distance from it); a child is outside a plane if even its corner farthest
/// along the normal is. The distance is that from the origin to the box, less the origins'
/// spread, rounded down past f32's rounding and the rays' direction length (1 +- 2^-23).
#[inline(always)]
fn bundle_test_scalar(node: &Node, bundle: &Bundle) -> (u32, [f32; WIDTH]) {
    let o = bundle.origin;
    let mut bx = [[0f32; WIDTH]; 6];
    for (p, planes) in bx.iter_mut().enumerate() {
        let a = p / 2;
        for i in 0..WIDTH {
            planes[i] = (node.origin[a] + node.planes[p][i] as f32 * node.scale[a]) - o[a];
        }
    }
    let mut outside = [0u32; 9];
    for (k, &(n, c)) in bundle.planes.iter().enumerate() {
        let pick = |a: usize| if n[a] >= 0.0 { &bx[2 * a + 1] } else { &bx[2 * a] };
        let (px, py, pz) = (pick(0), pick(1), pick(2));
        for i in 0..WIDTH {
            outside[k] |= ((((n[0] * px[i] + n[1] * py[i]) + n[2] * pz[i]) + c < 0.0) as u32) << i;
        }
    }
    let mut near = [0f32; WIDTH];
    for (i, near) in near.iter_mut().enumerate() {
        let g = |a: usize| max_ps(max_ps(bx[2 * a][i], -bx[2 * a + 1][i]), 0.0);
        let (gx, gy, gz) = (g(0), g(1), g(2));
        *near = (((gx * gx + gy * gy) + gz * gz).sqrt() - bundle.radius) * (1.0 - 1e-5);
    }
    (node.used & !bundle_culled(&outside), near)
}

/// The children outside the near plane, or outside both planes of some side.
#[inline(always)]
fn bundle_culled(outside: &[u32; 9]) -> u32 {
    outside[8]
        | (outside[0] & outside[1])
        | (outside[2] & outside[3])
        | (outside[4] & outside[5])
        | (outside[6] & outside[7])
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use std::mem::MaybeUninit;

    use super::{bundle_culled, BoxRay, Bundle, FlatNode, Node, QuadHits, TriRay, FAR_SCALE, WIDTH};
    use crate::math::gamma;

    /// [`super::super::intersect_triangle`] on four lanes: the same IEEE operations in the
    /// same order (no fused multiply-add), so each lane's values are the scalar test's, bit for
    /// bit; `None` if one of the `n` lanes has an edge function exactly 0 (the scalar test then
    /// takes f64 arithmetic for it).
    #[inline(always)]
    pub unsafe fn quad_sse(
        block: *const f32,
        n: usize,
        r: &TriRay,
        tmin: f32,
        tmax: f32,
        out: &mut MaybeUninit<QuadHits>,
    ) -> Option<u32> {
        let [kx, ky, kz] = r.k;
        let valid = (1u32 << n) - 1;
        // Lanes past `n` hold whatever follows (the next coordinates, or padding): masked out.
        // Each vertex's arrays start 3 n apart; an axis's array k n into them.
        let (xn, yn, zn) = (kx * n, ky * n, kz * n);
        let vertices = [block, block.add(3 * n), block.add(6 * n)];
        let load = |v: usize, an: usize| _mm_loadu_ps(vertices[v].add(an));
        let (ox, oy, oz) = (_mm_set1_ps(r.o[0]), _mm_set1_ps(r.o[1]), _mm_set1_ps(r.o[2]));
        let (sx, sy, sz) = (_mm_set1_ps(r.s[0]), _mm_set1_ps(r.s[1]), _mm_set1_ps(r.s[2]));
        // Vertex v relative to the origin, on the permuted axes, sheared.
        let vertex = |v: usize| {
            let az = _mm_sub_ps(load(v, zn), oz);
            let x = _mm_add_ps(_mm_sub_ps(load(v, xn), ox), _mm_mul_ps(sx, az));
            let y = _mm_add_ps(_mm_sub_ps(load(v, yn), oy), _mm_mul_ps(sy, az));
            (x, y, az)
        };
        let ((ax, ay, a_z), (bx, by, b_z), (cx, cy, c_z)) = (vertex(0), vertex(1), vertex(2));
        let u = _mm_sub_ps(_mm_mul_ps(cx, by), _mm_mul_ps(cy, bx));
        let v = _mm_sub_ps(_mm_mul_ps(ax, cy), _mm_mul_ps(ay, cx));
        let w = _mm_sub_ps(_mm_mul_ps(bx, ay), _mm_mul_ps(by, ax));
        let zero = _mm_setzero_ps();
        let on_edge =
            _mm_or_ps(_mm_or_ps(_mm_cmpeq_ps(u, zero), _mm_cmpeq_ps(v, zero)), _mm_cmpeq_ps(w, zero));
        if _mm_movemask_ps(on_edge) as u32 & valid != 0 {
            return None;
        }
        let any_neg =
            _mm_or_ps(_mm_or_ps(_mm_cmplt_ps(u, zero), _mm_cmplt_ps(v, zero)), _mm_cmplt_ps(w, zero));
        let any_pos =
            _mm_or_ps(_mm_or_ps(_mm_cmpgt_ps(u, zero), _mm_cmpgt_ps(v, zero)), _mm_cmpgt_ps(w, zero));
        let mut miss = _mm_and_ps(any_neg, any_pos);
        let det = _mm_add_ps(_mm_add_ps(u, v), w);
        miss = _mm_or_ps(miss, _mm_cmpeq_ps(det, zero));
        // Most leaves are passed by: out as soon as every lane has missed.
        if !(_mm_movemask_ps(miss) as u32) & valid == 0 {
            return Some(0);
        }
        let (az, bz, cz) = (_mm_mul_ps(sz, a_z), _mm_mul_ps(sz, b_z), _mm_mul_ps(sz, c_z));
        let t_scaled = _mm_add_ps(_mm_add_ps(_mm_mul_ps(u, az), _mm_mul_ps(v, bz)), _mm_mul_ps(w, cz));
        let (lo, hi) = (_mm_mul_ps(_mm_set1_ps(tmin), det), _mm_mul_ps(_mm_set1_ps(tmax), det));
        let neg_out = _mm_or_ps(_mm_cmpge_ps(t_scaled, lo), _mm_cmplt_ps(t_scaled, hi));
        let pos_out = _mm_or_ps(_mm_cmple_ps(t_scaled, lo), _mm_cmpgt_ps(t_scaled, hi));
        miss = _mm_or_ps(miss, _mm_and_ps(_mm_cmplt_ps(det, zero), neg_out));
        miss = _mm_or_ps(miss, _mm_and_ps(_mm_cmpgt_ps(det, zero), pos_out));
        if !(_mm_movemask_ps(miss) as u32) & valid == 0 {
            return Some(0);
        }
        let inv_det = _mm_div_ps(_mm_set1_ps(1.0), det);
        let t = _mm_mul_ps(t_scaled, inv_det);
        // The error bound of t (all operands are magnitudes, so max_ps is f32::max here).
        let abs = |x: __m128| _mm_andnot_ps(_mm_set1_ps(-0.0), x);
        let max3 = |a: __m128, b: __m128, c: __m128| _mm_max_ps(_mm_max_ps(abs(a), abs(b)), abs(c));
        let g = |n: i32| _mm_set1_ps(gamma(n));
        let max_zt = max3(az, bz, cz);
        let delta_z = _mm_mul_ps(g(3), max_zt);
        let max_xt = max3(ax, bx, cx);
        let max_yt = max3(ay, by, cy);
        let delta_x = _mm_mul_ps(g(5), _mm_add_ps(max_xt, max_zt));
        let delta_y = _mm_mul_ps(g(5), _mm_add_ps(max_yt, max_zt));
        let delta_e = _mm_mul_ps(
            _mm_set1_ps(2.0),
            _mm_add_ps(
                _mm_add_ps(_mm_mul_ps(_mm_mul_ps(g(2), max_xt), max_yt), _mm_mul_ps(delta_y, max_xt)),
                _mm_mul_ps(delta_x, max_yt),
            ),
        );
        let max_e = max3(u, v, w);
        let delta_t = _mm_mul_ps(
            _mm_mul_ps(
                _mm_set1_ps(3.0),
                _mm_add_ps(
                    _mm_add_ps(_mm_mul_ps(_mm_mul_ps(g(3), max_e), max_zt), _mm_mul_ps(delta_e, max_zt)),
                    _mm_mul_ps(delta_z, max_e),
                ),
            ),
            abs(inv_det),
        );
        miss = _mm_or_ps(miss, _mm_cmple_ps(t, delta_t));
        let mask = !(_mm_movemask_ps(miss) as u32) & valid;
        if mask == 0 {
            return Some(0);
        }
        let store = |x: __m128| {
            let mut a = [0.0f32; 4];
            _mm_storeu_ps(a.as_mut_ptr(), x);
            a
        };
        out.write(QuadHits {
            t: store(t),
            t_scaled: store(t_scaled),
            det: store(det),
            b1: store(_mm_mul_ps(v, inv_det)),
            b2: store(_mm_mul_ps(w, inv_det)),
        });
        Some(mask)
    }

    /// [`super::super::shapes::intersect_sphere`] of one ray against up to four balls (centres
    /// `c`, radii squared `rr`, as that function squares them), one a lane: the same IEEE
    /// operations in the same order, for the lanes in `alive`. Returns the lanes that hit
    /// within `[tmin, tmax)`, and their distances.
    #[inline(always)]
    pub unsafe fn balls_sse(
        ray: &crate::geometry::Ray,
        c: &[[f32; 4]; 3],
        rr: [f32; 4],
        alive: u32,
        tmax: f32,
    ) -> (u32, [f32; 4]) {
        use _mm_add_ps as add;
        use _mm_mul_ps as mul;
        use _mm_sub_ps as sub;
        let (o, d) = (ray.o, ray.d);
        let f = [0, 1, 2].map(|k| sub(_mm_set1_ps(o[k]), _mm_loadu_ps(c[k].as_ptr())));
        let ds = [0, 1, 2].map(|k| _mm_set1_ps(d[k]));
        macro_rules! dot {
            ($a:expr, $b:expr) => {
                add(add(mul($a[0], $b[0]), mul($a[1], $b[1])), mul($a[2], $b[2]))
            };
        }
        let a = _mm_set1_ps(d.length_squared());
        let b = dot!(f, ds);
        let rr = _mm_loadu_ps(rr.as_ptr());
        let cc = sub(dot!(f, f), rr);
        let ba = _mm_div_ps(b, a);
        let l = [sub(f[0], mul(ds[0], ba)), sub(f[1], mul(ds[1], ba)), sub(f[2], mul(ds[2], ba))];
        let disc = mul(a, sub(rr, dot!(l, l)));
        let neg = _mm_movemask_ps(_mm_cmplt_ps(disc, _mm_setzero_ps())) as u32;
        if !neg & alive == 0 {
            return (0, [0.0; 4]);
        }
        let root = _mm_sqrt_ps(disc);
        let sign = _mm_set1_ps(-0.0);
        // copysign(root, b), then negated.
        let signed = _mm_or_ps(_mm_andnot_ps(sign, root), _mm_and_ps(sign, b));
        let q = _mm_xor_ps(add(b, signed), sign);
        let (t0, t1) = (_mm_div_ps(q, a), _mm_div_ps(cc, q));
        // (Selections by masks, all ones or all zeros: SSE2, as the SSE kernel runs on CPUs
        // without SSE4.1's blend.)
        let select = |m: __m128, a: __m128, b: __m128| _mm_or_ps(_mm_and_ps(m, a), _mm_andnot_ps(m, b));
        // if t0 > t1, swap.
        let swap = _mm_cmpgt_ps(t0, t1);
        let (t0, t1) = (select(swap, t1, t0), select(swap, t0, t1));
        let (tmin, tmax) = (_mm_set1_ps(ray.tmin), _mm_set1_ps(tmax));
        let in0 = _mm_and_ps(_mm_cmpgt_ps(t0, tmin), _mm_cmplt_ps(t0, tmax));
        let in1 = _mm_and_ps(_mm_cmpgt_ps(t1, tmin), _mm_cmplt_ps(t1, tmax));
        let hit = _mm_movemask_ps(_mm_or_ps(in0, in1)) as u32 & !neg & alive;
        let mut t = [0.0f32; 4];
        _mm_storeu_ps(t.as_mut_ptr(), select(in0, t0, t1));
        (hit, t)
    }

    /// [`super::super::intersect_triangle`] of one triangle (its vertices on the rays' permuted
    /// axes) against eight rays, one a lane: the same IEEE operations in the same order as
    /// [`quad_sse`] (hence as the scalar test), for the lanes in `alive`. Returns the lanes
    /// that hit closer than their `tmax`, the lanes whose ray passes exactly through an edge
    /// (the scalar test decides those), and the hits' distances and barycentrics.
    #[inline(always)]
    #[allow(clippy::type_complexity)]
    pub unsafe fn tri_lanes(
        r: &super::TriRayLanes,
        p: [[f32; 3]; 3],
        tmax: __m256,
        alive: u32,
    ) -> (u32, u32, [f32; 8], [f32; 8], [f32; 8]) {
        let none = [0.0f32; 8];
        let [ox, oy, oz] = r.o;
        let [sx, sy, sz] = r.s;
        // (Macros, not closures: this runs in the packet's inner loop, and a closure the
        // inliner leaves out of line passes its vectors through memory.)
        macro_rules! vertex {
            ($v:expr) => {{
                let az = _mm256_sub_ps(_mm256_set1_ps(p[$v][2]), oz);
                let x = _mm256_add_ps(_mm256_sub_ps(_mm256_set1_ps(p[$v][0]), ox), _mm256_mul_ps(sx, az));
                let y = _mm256_add_ps(_mm256_sub_ps(_mm256_set1_ps(p[$v][1]), oy), _mm256_mul_ps(sy, az));
                (x, y, az)
            }};
        }
        let ((ax, ay, a_z), (bx, by, b_z), (cx, cy, c_z)) = (vertex!(0), vertex!(1), vertex!(2));
        let u = _mm256_sub_ps(_mm256_mul_ps(cx, by), _mm256_mul_ps(cy, bx));
        let v = _mm256_sub_ps(_mm256_mul_ps(ax, cy), _mm256_mul_ps(ay, cx));
        let w = _mm256_sub_ps(_mm256_mul_ps(bx, ay), _mm256_mul_ps(by, ax));
        let zero = _mm256_setzero_ps();
        macro_rules! eq {
            ($a:expr) => {
                _mm256_cmp_ps::<_CMP_EQ_OQ>($a, zero)
            };
        }
        macro_rules! lt {
            ($a:expr, $b:expr) => {
                _mm256_cmp_ps::<_CMP_LT_OQ>($a, $b)
            };
        }
        macro_rules! gt {
            ($a:expr, $b:expr) => {
                _mm256_cmp_ps::<_CMP_GT_OQ>($a, $b)
            };
        }
        macro_rules! or {
            ($a:expr, $b:expr) => {
                _mm256_or_ps($a, $b)
            };
        }
        macro_rules! bits {
            ($a:expr) => {
                _mm256_movemask_ps($a) as u32
            };
        }
        let edge = bits!(or!(or!(eq!(u), eq!(v)), eq!(w))) & alive;
        let alive = alive & !edge;
        let any_neg = or!(or!(lt!(u, zero), lt!(v, zero)), lt!(w, zero));
        let any_pos = or!(or!(gt!(u, zero), gt!(v, zero)), gt!(w, zero));
        let det = _mm256_add_ps(_mm256_add_ps(u, v), w);
        let mut miss = or!(_mm256_and_ps(any_neg, any_pos), eq!(det));
        // Most triangles are passed by: out as soon as every lane has missed.
        if !bits!(miss) & alive == 0 {
            return (0, edge, none, none, none);
        }
        let (az, bz, cz) = (_mm256_mul_ps(sz, a_z), _mm256_mul_ps(sz, b_z), _mm256_mul_ps(sz, c_z));
        let t_scaled =
            _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(u, az), _mm256_mul_ps(v, bz)), _mm256_mul_ps(w, cz));
        let (lo, hi) = (_mm256_mul_ps(r.tmin, det), _mm256_mul_ps(tmax, det));
        let neg_out = or!(_mm256_cmp_ps::<_CMP_GE_OQ>(t_scaled, lo), lt!(t_scaled, hi));
        let pos_out = or!(_mm256_cmp_ps::<_CMP_LE_OQ>(t_scaled, lo), gt!(t_scaled, hi));
        miss = or!(miss, _mm256_and_ps(lt!(det, zero), neg_out));
        miss = or!(miss, _mm256_and_ps(gt!(det, zero), pos_out));
        if !bits!(miss) & alive == 0 {
            return (0, edge, none, none, none);
        }
        let inv_det = _mm256_div_ps(_mm256_set1_ps(1.0), det);
        let t = _mm256_mul_ps(t_scaled, inv_det);
        // The error bound of t, as `quad_sse` computes it.
        macro_rules! abs {
            ($x:expr) => {
                _mm256_andnot_ps(_mm256_set1_ps(-0.0), $x)
            };
        }
        macro_rules! max3 {
            ($a:expr, $b:expr, $c:expr) => {
                _mm256_max_ps(_mm256_max_ps(abs!($a), abs!($b)), abs!($c))
            };
        }
        macro_rules! g {
            ($n:expr) => {
                _mm256_set1_ps(gamma($n))
            };
        }
        let max_zt = max3!(az, bz, cz);
        let delta_z = _mm256_mul_ps(g!(3), max_zt);
        let max_xt = max3!(ax, bx, cx);
        let max_yt = max3!(ay, by, cy);
        let delta_x = _mm256_mul_ps(g!(5), _mm256_add_ps(max_xt, max_zt));
        let delta_y = _mm256_mul_ps(g!(5), _mm256_add_ps(max_yt, max_zt));
        let delta_e = _mm256_mul_ps(
            _mm256_set1_ps(2.0),
            _mm256_add_ps(
                _mm256_add_ps(
                    _mm256_mul_ps(_mm256_mul_ps(g!(2), max_xt), max_yt),
                    _mm256_mul_ps(delta_y, max_xt),
                ),
                _mm256_mul_ps(delta_x, max_yt),
            ),
        );
        let max_e = max3!(u, v, w);
        let delta_t = _mm256_mul_ps(
            _mm256_mul_ps(
                _mm256_set1_ps(3.0),
                _mm256_add_ps(
                    _mm256_add_ps(
                        _mm256_mul_ps(_mm256_mul_ps(g!(3), max_e), max_zt),
                        _mm256_mul_ps(delta_e, max_zt),
                    ),
                    _mm256_mul_ps(delta_z, max_e),
                ),
            ),
            abs!(inv_det),
        );
        miss = or!(miss, _mm256_cmp_ps::<_CMP_LE_OQ>(t, delta_t));
        // And closer than the ray's closest hit so far, as the leaf loop asks of a hit.
        let closer = lt!(t, tmax);
        let accept = !bits!(miss) & bits!(closer) & alive;
        if accept == 0 {
            return (0, edge, none, none, none);
        }
        macro_rules! store {
            ($x:expr) => {{
                let mut a = [0.0f32; 8];
                _mm256_storeu_ps(a.as_mut_ptr(), $x);
                a
            }};
        }
        (accept, edge, store!(t), store!(_mm256_mul_ps(v, inv_det)), store!(_mm256_mul_ps(w, inv_det)))
    }

    /// [`super::super::shapes::intersect_sphere`] of `ball` against eight rays, one a lane: the
    /// same IEEE operations in the same order, for the lanes in `alive`. Returns the lanes that
    /// hit within their `[tmin, tmax)`, and the distances.
    #[inline(always)]
    pub unsafe fn sphere_lanes(
        r: &super::SphereRayLanes,
        ball: &crate::geometry::Sphere,
        tmax: __m256,
        alive: u32,
    ) -> (u32, [f32; 8]) {
        use _mm256_add_ps as add;
        use _mm256_mul_ps as mul;
        use _mm256_sub_ps as sub;
        macro_rules! dot {
            ($a:expr, $b:expr) => {
                add(add(mul($a[0], $b[0]), mul($a[1], $b[1])), mul($a[2], $b[2]))
            };
        }
        let c = ball.center;
        let f = [
            sub(r.o[0], _mm256_set1_ps(c.x)),
            sub(r.o[1], _mm256_set1_ps(c.y)),
            sub(r.o[2], _mm256_set1_ps(c.z)),
        ];
        let a = dot!(r.d, r.d);
        let b = dot!(f, r.d);
        let rr = _mm256_set1_ps(ball.radius * ball.radius);
        let cc = sub(dot!(f, f), rr);
        let ba = _mm256_div_ps(b, a);
        let l = [sub(f[0], mul(r.d[0], ba)), sub(f[1], mul(r.d[1], ba)), sub(f[2], mul(r.d[2], ba))];
        let disc = mul(a, sub(rr, dot!(l, l)));
        let neg = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(disc, _mm256_setzero_ps())) as u32;
        if !neg & alive == 0 {
            return (0, [0.0; 8]);
        }
        let root = _mm256_sqrt_ps(disc);
        let sign = _mm256_set1_ps(-0.0);
        // copysign(root, b), then negated.
        let signed = _mm256_or_ps(_mm256_andnot_ps(sign, root), _mm256_and_ps(sign, b));
        let q = _mm256_xor_ps(add(b, signed), sign);
        let (t0, t1) = (_mm256_div_ps(q, a), _mm256_div_ps(cc, q));
        // if t0 > t1, swap.
        let swap = _mm256_cmp_ps::<_CMP_GT_OQ>(t0, t1);
        let (t0, t1) = (_mm256_blendv_ps(t0, t1, swap), _mm256_blendv_ps(t1, t0, swap));
        let in0 =
            _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(t0, r.tmin), _mm256_cmp_ps::<_CMP_LT_OQ>(t0, tmax));
        let in1 =
            _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(t1, r.tmin), _mm256_cmp_ps::<_CMP_LT_OQ>(t1, tmax));
        let t = _mm256_blendv_ps(t1, t0, in0);
        let hit = _mm256_movemask_ps(_mm256_or_ps(in0, in1)) as u32 & !neg & alive;
        let mut out = [0.0f32; 8];
        _mm256_storeu_ps(out.as_mut_ptr(), t);
        (hit, out)
    }

    /// [`super::test_scalar`] on two halves of four lanes.
    #[inline(always)]
    pub unsafe fn test_sse(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        let mut tn = [0.0f32; WIDTH];
        let mut mask = 0;
        let zero = _mm_setzero_si128();
        for half in 0..2 {
            let mut near = _mm_set1_ps(tmin);
            let mut far = _mm_set1_ps(tmax);
            for a in 0..3 {
                let (origin, scale) = (_mm_set1_ps(node.origin[a]), _mm_set1_ps(node.scale[a]));
                let plane = |p: usize| {
                    let q = (node.planes[p].as_ptr().add(4 * half) as *const i32).read_unaligned();
                    let q = _mm_unpacklo_epi16(_mm_unpacklo_epi8(_mm_cvtsi32_si128(q), zero), zero);
                    _mm_add_ps(origin, _mm_mul_ps(_mm_cvtepi32_ps(q), scale))
                };
                let (o, inv) = (_mm_set1_ps(r.o[a]), _mm_set1_ps(r.inv[a]));
                near = _mm_max_ps(_mm_mul_ps(_mm_sub_ps(plane(r.near[a]), o), inv), near);
                far = _mm_min_ps(_mm_mul_ps(_mm_sub_ps(plane(r.far[a]), o), inv), far);
            }
            _mm_storeu_ps(tn.as_mut_ptr().add(4 * half), near);
            let hit = _mm_cmple_ps(near, _mm_mul_ps(far, _mm_set1_ps(FAR_SCALE)));
            mask |= (_mm_movemask_ps(hit) as u32) << (4 * half);
        }
        (mask & node.used, tn)
    }

    /// [`super::test_scalar`] on all eight lanes at once (AVX2 widens the bytes). A plane is
    /// decoded by one fused multiply-add: the product `q * scale` (an integer below 256 times a
    /// power of two) is exact, so the fused and the separate operations round the same sum once
    /// and give the same bits (short of `q * scale` overflowing, which takes a node spanning
    /// about 1e38).
    #[inline(always)]
    pub unsafe fn test_avx2(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        let plane = |p: usize| {
            let a = p / 2;
            let q = _mm_loadl_epi64(node.planes[p].as_ptr() as *const __m128i);
            let (origin, scale) = (_mm256_set1_ps(node.origin[a]), _mm256_set1_ps(node.scale[a]));
            _mm256_fmadd_ps(_mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(q)), scale, origin)
        };
        slabs_avx2(plane, node.used, r, tmin, tmax)
    }

    /// [`test_avx2`] on a node's decoded planes ([`FlatNode`]): the same boxes.
    #[inline(always)]
    pub unsafe fn test_avx2_flat(node: &FlatNode, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        slabs_avx2(|p| _mm256_load_ps(node.planes[p].as_ptr()), node.used, r, tmin, tmax)
    }

    /// The slab test of eight boxes whose plane `p` (as [`super::Node::planes`]) `plane`
    /// gives, for the lanes in `used`.
    #[inline(always)]
    unsafe fn slabs_avx2(
        plane: impl Fn(usize) -> __m256,
        used: u32,
        r: &BoxRay,
        tmin: f32,
        tmax: f32,
    ) -> (u32, [f32; WIDTH]) {
        let mut near = _mm256_set1_ps(tmin);
        let mut far = _mm256_set1_ps(tmax);
        for a in 0..3 {
            let (o, inv) = (_mm256_set1_ps(r.o[a]), _mm256_set1_ps(r.inv[a]));
            near = _mm256_max_ps(_mm256_mul_ps(_mm256_sub_ps(plane(r.near[a]), o), inv), near);
            far = _mm256_min_ps(_mm256_mul_ps(_mm256_sub_ps(plane(r.far[a]), o), inv), far);
        }
        let mut tn = [0.0f32; WIDTH];
        _mm256_storeu_ps(tn.as_mut_ptr(), near);
        let hit = _mm256_cmp_ps::<_CMP_LE_OQ>(near, _mm256_mul_ps(far, _mm256_set1_ps(FAR_SCALE)));
        (_mm256_movemask_ps(hit) as u32 & used, tn)
    }

    /// [`super::bundle_test_scalar`] in one 256-bit register: the same IEEE operations in
    /// the same order.
    #[inline(always)]
    pub unsafe fn bundle_test_avx2(node: &Node, bundle: &Bundle) -> (u32, [f32; WIDTH]) {
        let o = bundle.origin;
        let plane = |p: usize| {
            let a = p / 2;
            let q = _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(_mm_loadl_epi64(node.planes[p].as_ptr().cast())));
            let decoded = _mm256_add_ps(
                _mm256_set1_ps(node.origin[a]),
                _mm256_mul_ps(q, _mm256_set1_ps(node.scale[a])),
            );
            _mm256_sub_ps(decoded, _mm256_set1_ps(o[a]))
        };
        let bx = [plane(0), plane(1), plane(2), plane(3), plane(4), plane(5)];
        let mut outside = [0u32; 9];
        for (k, &(n, c)) in bundle.planes.iter().enumerate() {
            let pick = |a: usize| if n[a] >= 0.0 { bx[2 * a + 1] } else { bx[2 * a] };
            let v = _mm256_add_ps(
                _mm256_add_ps(
                    _mm256_add_ps(
                        _mm256_mul_ps(_mm256_set1_ps(n[0]), pick(0)),
                        _mm256_mul_ps(_mm256_set1_ps(n[1]), pick(1)),
                    ),
                    _mm256_mul_ps(_mm256_set1_ps(n[2]), pick(2)),
                ),
                _mm256_set1_ps(c),
            );
            outside[k] = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(v, _mm256_setzero_ps())) as u32;
        }
        let zero = _mm256_setzero_ps();
        let g = |a: usize| {
            let neg_hi = _mm256_xor_ps(bx[2 * a + 1], _mm256_set1_ps(-0.0));
            // max_ps(max_ps(lo, -hi), 0): maxps(a, b) gives b where a > b fails, as max_ps.
            _mm256_max_ps(_mm256_max_ps(bx[2 * a], neg_hi), zero)
        };
        let (gx, gy, gz) = (g(0), g(1), g(2));
        let sq =
            _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(gx, gx), _mm256_mul_ps(gy, gy)), _mm256_mul_ps(gz, gz));
        let near = _mm256_mul_ps(
            _mm256_sub_ps(_mm256_sqrt_ps(sq), _mm256_set1_ps(bundle.radius)),
            _mm256_set1_ps(1.0 - 1e-5),
        );
        let mut out = [0f32; WIDTH];
        _mm256_storeu_ps(out.as_mut_ptr(), near);
        (node.used & !bundle_culled(&outside), out)
    }
}

/// A box test as a type, so that traversal is compiled once per kernel.
trait BoxTest {
    /// Whether the kernel tests a leaf's triangles together (`x86::quad_sse`, on x86-64).
    const QUADS: bool;
    /// # Safety
    /// The CPU must have the kernel's instructions.
    unsafe fn test(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]);
    /// Whether the kernel reads the tree's decoded planes ([`FlatNode`]) with `test_flat`.
    const FLAT: bool = false;
    /// [`BoxTest::test`] on a node's decoded planes, for kernels with `FLAT`.
    ///
    /// # Safety
    /// As `test`.
    #[inline(always)]
    unsafe fn test_flat(node: &FlatNode, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        let _ = (node, r, tmin, tmax);
        unreachable!("a kernel without FLAT reads the 8-bit planes")
    }
}
struct ScalarTest;
impl BoxTest for ScalarTest {
    const QUADS: bool = false;
    #[inline(always)]
    unsafe fn test(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        test_scalar(node, r, tmin, tmax)
    }
}
#[cfg(target_arch = "x86_64")]
struct SseTest;
#[cfg(target_arch = "x86_64")]
impl BoxTest for SseTest {
    const QUADS: bool = true;
    #[inline(always)]
    unsafe fn test(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        x86::test_sse(node, r, tmin, tmax)
    }
}
#[cfg(target_arch = "x86_64")]
struct AvxTest;
#[cfg(target_arch = "x86_64")]
impl BoxTest for AvxTest {
    const QUADS: bool = true;
    #[inline(always)]
    unsafe fn test(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        x86::test_avx2(node, r, tmin, tmax)
    }
}
/// [`AvxTest`] on the tree's decoded planes ([`FlatNode`]): the same boxes.
#[cfg(target_arch = "x86_64")]
struct AvxFlatTest;
#[cfg(target_arch = "x86_64")]
impl BoxTest for AvxFlatTest {
    const QUADS: bool = true;
    #[inline(always)]
    unsafe fn test(node: &Node, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        x86::test_avx2(node, r, tmin, tmax)
    }
    const FLAT: bool = true;
    #[inline(always)]
    unsafe fn test_flat(node: &FlatNode, r: &BoxRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
        x86::test_avx2_flat(node, r, tmin, tmax)
    }
}

/// A ray's constants for [`intersect_triangle`] on a quad: its origin and shear along the
/// axes [`RayPre`] permutes to (x, y, z).
#[derive(Clone, Copy)]
struct TriRay {
    k: [usize; 3],
    o: [f32; 3],
    s: [f32; 3],
}

impl TriRay {
    #[inline(always)]
    fn new(ray: &Ray, pre: &RayPre) -> TriRay {
        let k = [pre.kx, pre.ky, pre.kz];
        let o = ray.o.to_array();
        TriRay { k, o: k.map(|a| o[a]), s: [pre.sx, pre.sy, pre.sz] }
    }
}

/// What [`intersect_triangle`] computes on each lane of a quad, for the lanes that hit within
/// `[tmin, tmax]`: distances, scaled distances and determinants (to test them again against a
/// closer `tmax`) and barycentrics.
struct QuadHits {
    t: [f32; 4],
    t_scaled: [f32; 4],
    det: [f32; 4],
    b1: [f32; 4],
    b2: [f32; 4],
}

impl QuadHits {
    /// Whether lane `j`'s hit passes [`intersect_triangle`]'s test against `tmax`.
    #[inline(always)]
    fn within(&self, j: usize, tmax: f32) -> bool {
        let (ts, det) = (self.t_scaled[j], self.det[j]);
        if det < 0.0 {
            !(ts < tmax * det)
        } else {
            !(ts > tmax * det)
        }
    }
}

/// One closest-hit or any-hit query's state, handed to [`Accel::traverse`]'s leaf callback.
#[derive(Clone)]
struct Query<'a> {
    shapes: &'a [Shape],
    ray: &'a Ray,
    pre: RayPre,
    /// The closest hit so far: leaf-order primitive and its aux values.
    best: Option<(u32, Vec2)>,
    /// The last hit accepted inside an instance: the group tree's leaf-order primitive, its
    /// aux values and its distance in the group's space. When `best` is an instance, this is
    /// its hit (an instance reports only hits that are accepted).
    inner: Cell<(u32, Vec2, f32)>,
    /// The fibre piece the ray leaves, not tested (see [`Leaving`]).
    leaving: Option<Leaving>,
    /// A leaf the ray cannot meet again, not tested ([`SpawnedFrom`]); 0 (the root, never a
    /// leaf) for none.
    skip: u32,
    /// The leaf of the closest hit so far (`best`'s).
    leaf: u32,
}

impl<'a> Query<'a> {
    fn new(shapes: &'a [Shape], ray: &'a Ray) -> Query<'a> {
        Query::from(shapes, ray, SpawnedFrom::NOTHING, true)
    }

    /// A query fresh from [`Query::new`], along `ray` instead: only the ray and its
    /// constants change (the other fields are the same for every fresh query).
    #[inline(always)]
    fn aim(&mut self, ray: &'a Ray) {
        self.ray = ray;
        self.pre = RayPre::new(crate::math::load_apart(&ray.d));
    }

    /// A query of `ray`, spawned from `from`; its triangle constants only where `triangles`
    /// (else [`RayPre::UNUSED`]).
    #[inline(always)]
    fn from(shapes: &'a [Shape], ray: &'a Ray, from: SpawnedFrom, triangles: bool) -> Query<'a> {
        Query {
            shapes,
            ray,
            // (Read a coordinate at a time: `math::load_apart`.)
            pre: if triangles { RayPre::new(crate::math::load_apart(&ray.d)) } else { RayPre::UNUSED },
            best: None,
            inner: Cell::new((0, Vec2::ZERO, 0.0)),
            leaving: from.piece,
            skip: from.leaf,
            leaf: 0,
        }
    }
}

/// Primitives per bottom-level build when a scene has more (see [`Accel::build`]): obvhs'
/// scratch is held for this many at a time.
pub const BATCH: usize = 1 << 18;

/// The wide tree being built: its nodes (node 0 is the root) and its primitives in leaf order.
struct Builder<'a> {
    shapes: &'a [Shape],
    /// Whether the tree is built over fibre pieces ([`PIECE`]), one a leaf.
    pieces: bool,
    nodes: Vec<Node>,
    prims: Vec<PrimRef>,
    tris: LeafTris,
}

impl Builder<'_> {
    /// Builds a tree over `units` into node `slot` and appends their primitives in leaf
    /// order; returns the tree's box and depth.
    fn bottom(&mut self, units: &[Unit], params: BvhBuildParams, slot: usize) -> (Aabb, usize) {
        let shapes = self.shapes;
        let aabbs: Vec<Aabb> = units.iter().map(|u| unit_bounds(shapes, u)).collect();
        let mut bvh2 = build_bvh2(&aabbs, params, &mut Default::default());
        drop(aabbs);
        if self.pieces {
            leaves_in_tree_order(&mut bvh2);
        }
        merge_triangle_leaves(&mut bvh2, self.pieces, |k| units[k as usize].first.shape & TRIANGLE != 0);
        // Each unit's primitives in leaf order; `start[i]` is where the unit at position `i`
        // of the tree's order begins among them.
        let mut order = Vec::with_capacity(units.iter().map(|u| u.len as usize).sum());
        let mut start = Vec::with_capacity(units.len() + 1);
        for &k in &bvh2.primitive_indices {
            let u = units[k as usize];
            start.push(order.len() as u32);
            order.extend((0..u.len).map(|j| PrimRef { index: u.first.index + j, ..u.first }));
        }
        start.push(order.len() as u32);
        let span = |node: &obvhs::bvh2::node::Bvh2Node| {
            start[node.first_index as usize]..start[(node.first_index + node.prim_count) as usize]
        };
        let offset = self.prims.len() as u32;
        let depth = self.collapse(&bvh2, slot, |leaf| {
            let range = span(leaf);
            assert!((1..=LEAF_MAX).contains(&(range.len() as u32)), "a leaf of {} primitives", range.len());
            let all_tris =
                order[range.start as usize..range.end as usize].iter().all(|p| p.shape & TRIANGLE != 0);
            LEAF | if all_tris { TRI_LEAF } else { 0 }
                | (range.len() as u32 - 1) << FIRST_BITS
                | (offset + range.start)
        });
        // Leaf by leaf, in leaf order: its triangles become one block of `tris`. (The leaves
        // the tree reaches: merged leaves leave their former children behind, unreached.)
        let mut leaves: Vec<(usize, usize)> = Vec::new();
        let mut todo = vec![0usize];
        while let Some(n) = todo.pop() {
            let node = &bvh2.nodes[n];
            if node.is_leaf() {
                let range = span(node);
                leaves.push((range.start as usize, range.len()));
            } else {
                todo.extend([node.first_index as usize, node.first_index as usize + 1]);
            }
        }
        leaves.sort_unstable();
        let mut tris = Vec::with_capacity(LEAF_MAX as usize);
        for (first, count) in leaves {
            let start = self.prims.len();
            tris.clear();
            for mut p in order[first..first + count].iter().copied() {
                match &shapes[(p.shape & SHAPE) as usize].geometry {
                    Geometry::Mesh(m) if p.shape & TRIANGLE != 0 => {
                        tris.push((m.tri(p.index as usize), p.index));
                        p.index = tris.len() as u32 - 1; // the lane, until the block is placed
                    }
                    _ => {}
                }
                self.prims.push(p);
            }
            if !tris.is_empty() {
                let slot0 = self.tris.push(&tris);
                for p in self.prims[start..].iter_mut().filter(|p| p.shape & TRIANGLE != 0) {
                    p.index += slot0;
                }
                if tris.len() == count && coplanar(tris.iter().map(|t| &t.0)) {
                    self.prims[start].shape |= PLANAR;
                }
            }
        }
        (*bvh2.nodes[0].aabb(), depth)
    }

    /// Collapses binary tree `b2` into wide nodes, its root into node `slot`, choosing the
    /// wide tree of least surface-area cost (Ylitie et al. 2017, section 4): the sum of the
    /// areas of its wide nodes, each the chance that a ray meets the node and tests its eight
    /// boxes. The leaves are fixed (each takes one child slot whatever the tree), so they add
    /// the same to every choice. `leaf` gives a binary leaf's child reference. Returns the depth.
    fn collapse(
        &mut self,
        b2: &obvhs::bvh2::Bvh2,
        slot: usize,
        leaf: impl Fn(&obvhs::bvh2::node::Bvh2Node) -> u32,
    ) -> usize {
        let plan = SlotPlan::of(&b2.nodes);
        let b2 = &b2.nodes;
        let nodes = &mut self.nodes;
        let mut todo = vec![(slot, 0usize, 1usize)]; // (wide node, binary node, depth)
        let mut depth = 1;
        let mut kids = Vec::with_capacity(WIDTH);
        while let Some((w, n, level)) = todo.pop() {
            depth = depth.max(level);
            kids.clear();
            if b2[n].is_leaf() {
                kids.push(n);
            } else {
                plan.open(b2, n, &mut kids);
            }
            let boxes: Vec<(Vec3A, Vec3A)> =
                kids.iter().map(|&k| (b2[k].aabb().min, b2[k].aabb().max)).collect();
            nodes[w] = Node::quantise(&boxes);
            for (lane, &k) in kids.iter().enumerate() {
                let node = &b2[k];
                nodes[w].child[lane] = if node.is_leaf() {
                    leaf(node)
                } else {
                    nodes.push(EMPTY_NODE);
                    todo.push((nodes.len() - 1, k, level + 1));
                    nodes.len() as u32 - 1
                };
            }
        }
        depth
    }
}

/// For each node of a binary tree reached from its root, the least cost of its subtree given
/// `i` slots (1 to [`WIDTH`]) of the wide node above it, and how it spends them.
struct SlotPlan {
    /// `cost[n][i - 1]`: with one slot, node `n` is a wide node of its own (its area plus the
    /// cost of its children spread over [`WIDTH`] slots); with more, the better of that and
    /// its two children sharing the slots. A leaf costs 0 (the same in every tree).
    cost: Vec<[f32; WIDTH]>,
    /// `split[n][i - 1]`: 0 where `n` takes one slot; otherwise the left child's slots in the
    /// low four bits and the right child's in the high four. `split[n][0]` is the split of
    /// [`WIDTH`] slots that `n` makes as a wide node.
    split: Vec<[u8; WIDTH]>,
}

impl SlotPlan {
    fn of(b2: &[obvhs::bvh2::node::Bvh2Node]) -> SlotPlan {
        let mut plan = SlotPlan { cost: vec![[0.0; WIDTH]; b2.len()], split: vec![[0; WIDTH]; b2.len()] };
        if b2.is_empty() {
            return plan;
        }
        let mut todo = vec![(0usize, false)];
        while let Some((n, second)) = todo.pop() {
            if b2[n].is_leaf() {
                continue;
            }
            let (a, b) = (b2[n].first_index as usize, b2[n].first_index as usize + 1);
            if !second {
                todo.extend([(n, true), (a, false), (b, false)]);
                continue;
            }
            // `spread[j - 1]`: the least cost of the two children sharing `j` slots. (Each
            // starts from the split (1, j - 1), so that a split is always made, whatever the
            // areas: an infinite or NaN one would otherwise leave none.)
            let mut spread = [(f32::INFINITY, 0u8); WIDTH];
            for j in 2..=WIDTH {
                spread[j - 1] = (plan.cost[a][0] + plan.cost[b][j - 2], (1 | (j - 1) << 4) as u8);
                for k in 2..j {
                    let c = plan.cost[a][k - 1] + plan.cost[b][j - k - 1];
                    if c < spread[j - 1].0 {
                        spread[j - 1] = (c, (k | (j - k) << 4) as u8);
                    }
                }
            }
            let (mut cost, mut split) = ([0.0; WIDTH], [0u8; WIDTH]);
            cost[0] = b2[n].aabb().half_area() + spread[WIDTH - 1].0;
            split[0] = spread[WIDTH - 1].1;
            for i in 2..=WIDTH {
                (cost[i - 1], split[i - 1]) = if spread[i - 1].0 < cost[i - 2] {
                    spread[i - 1]
                } else {
                    (cost[i - 2], split[i - 2] * u8::from(i > 2))
                };
            }
            plan.cost[n] = cost;
            plan.split[n] = split;
        }
        plan
    }

    /// Appends the children of inner node `n` as a wide node: the binary nodes its slots hold.
    fn open(&self, b2: &[obvhs::bvh2::node::Bvh2Node], n: usize, kids: &mut Vec<usize>) {
        self.share(b2, n, self.split[n][0], kids);
    }

    /// Appends what inner node `n`'s two children hold, sharing slots by `split`.
    fn share(&self, b2: &[obvhs::bvh2::node::Bvh2Node], n: usize, split: u8, kids: &mut Vec<usize>) {
        let first = b2[n].first_index as usize;
        self.fill(b2, first, (split & 15) as usize, kids);
        self.fill(b2, first + 1, (split >> 4) as usize, kids);
    }

    /// Appends what node `n` holds given `slots` slots: itself, or its children's share.
    fn fill(&self, b2: &[obvhs::bvh2::node::Bvh2Node], n: usize, slots: usize, kids: &mut Vec<usize>) {
        match if slots == 1 || b2[n].is_leaf() { 0 } else { self.split[n][slots - 1] } {
            0 => kids.push(n),
            split => self.share(b2, n, split, kids),
        }
    }
}

/// Renumbers `b2`'s leaves of one primitive each (obvhs leaves them in the order of its
/// input) in the order a depth-first walk meets them, so that a subtree's primitives are one
/// run of its order, as `merge_triangle_leaves` needs.
fn leaves_in_tree_order(b2: &mut obvhs::bvh2::Bvh2) {
    if b2.nodes.is_empty() {
        return;
    }
    let mut order = Vec::with_capacity(b2.primitive_indices.len());
    let mut todo = vec![0usize];
    while let Some(n) = todo.pop() {
        let node = b2.nodes[n];
        if node.is_leaf() {
            debug_assert_eq!(node.prim_count, 1);
            b2.nodes[n].first_index = order.len() as u32;
            order.push(b2.primitive_indices[node.first_index as usize]);
        } else {
            todo.extend([node.first_index as usize + 1, node.first_index as usize]);
        }
    }
    b2.primitive_indices = order;
}

/// Turns into one leaf each subtree of `b2` of at most [`LEAF_MAX`] triangles (`is_tri` of a
/// primitive index) held in one run of its primitive order, where the SAH says so with the
/// x86 kernels' costs: they test a leaf's triangles in four lanes at once, so a leaf costs the
/// same for one triangle as for four, and a subtree's leaves (whose boxes the wide node above
/// tests in parallel) cost the sum of their areas. A node becomes a leaf when its box's area is
/// at most that sum: the two triangles of a rectangle, whose boxes are both the rectangle's,
/// become one leaf tested once instead of two (obvhs' SAH, which prices a leaf by its count,
/// keeps them apart). Leaves only grow; a merged node's former children stay, unreached. The
/// portable kernel's leaves cost by count, but the tree is the same on every target. With
/// `pieces` (a tree over fibre pieces, whose leaves obvhs leaves one primitive each) every
/// such subtree becomes a leaf, as obvhs' own collapse joins nearly all of them in other trees.
fn merge_triangle_leaves(b2: &mut obvhs::bvh2::Bvh2, pieces: bool, is_tri: impl Fn(u32) -> bool) {
    let nodes = &mut b2.nodes;
    if nodes.is_empty() {
        return;
    }
    // A node's cost: the area its leaves are tested over (None: not a leaf of triangles).
    let mut cost = vec![None::<f32>; nodes.len()];
    // Post-order from the root: a node is visited again (second) once its children are done.
    let mut todo = vec![(0usize, false)];
    while let Some((n, second)) = todo.pop() {
        let node = nodes[n];
        if node.is_leaf() {
            let range = node.first_index..node.first_index + node.prim_count;
            if range.clone().all(|i| is_tri(b2.primitive_indices[i as usize])) {
                cost[n] = Some(node.aabb().half_area());
            }
            continue;
        }
        let (a, b) = (node.first_index as usize, node.first_index as usize + 1);
        if !second {
            todo.extend([(n, true), (a, false), (b, false)]);
            continue;
        }
        let (Some(ca), Some(cb)) = (cost[a], cost[b]) else { continue };
        let (na, nb) = (nodes[a], nodes[b]);
        let (lo, hi) = if na.first_index < nb.first_index { (na, nb) } else { (nb, na) };
        let count = na.prim_count + nb.prim_count;
        let area = node.aabb().half_area();
        if count <= LEAF_MAX
            && lo.first_index + lo.prim_count == hi.first_index
            && (pieces || area <= ca + cb)
        {
            nodes[n].prim_count = count;
            nodes[n].first_index = lo.first_index;
            cost[n] = Some(area);
        }
        // Otherwise it stays an inner node, and so does every node above it (cost None).
    }
}

/// Whether the triangles lie in one plane, to within [`FLAT`]: each triangle's normal within
/// `FLAT` radians of the first's, and every vertex within `FLAT` times the triangles' extent
/// of the first's plane (none degenerate). The two triangles of a transformed rectangle are,
/// through the rounding of their corners, unless it is small and far from the origin. A ray
/// leaving one of them can then meet another only if it leaves within about `FLAT` radians of
/// the plane, where the surface's cosine is below `FLAT` (and its hit would owe as much to the
/// vertices' rounding as to the geometry).
fn coplanar<'a>(tris: impl Iterator<Item = &'a [Vec3; 3]> + Clone) -> bool {
    let unit = |t: &[Vec3; 3]| {
        let [a, b, c] = t.map(|v| v.as_dvec3());
        (b - a).cross(c - a).try_normalize()
    };
    let Some(first) = tris.clone().next() else { return false };
    let (Some(n), a) = (unit(first), first[0].as_dvec3()) else { return false };
    let (lo, hi) = tris
        .clone()
        .flatten()
        .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    let extent = (hi - lo).as_dvec3().length();
    tris.into_iter().all(|t| {
        unit(t).is_some_and(|m| m.cross(n).length() <= FLAT)
            && t.iter().all(|v| n.dot(v.as_dvec3() - a).abs() <= FLAT * extent)
    })
}

/// How far from one plane [`coplanar`] lets triangles be (radians, and a fraction of their
/// extent): about ten times the rounding of a rectangle's corners near the origin.
const FLAT: f64 = 1e-6;

/// A unit's box: its primitives' boxes together.
fn unit_bounds(shapes: &[Shape], u: &Unit) -> Aabb {
    let shape = &shapes[(u.first.shape & SHAPE) as usize];
    let (mut lo, mut hi) = shape.prim_bounds(u.first.index as usize);
    for j in 1..u.len {
        let (l, h) = shape.prim_bounds((u.first.index + j) as usize);
        (lo, hi) = (lo.min(l), hi.max(h));
    }
    Aabb::new(Vec3A::from(lo), Vec3A::from(hi))
}

/// `units` (all `count` of them) sorted by the Morton code of their box centres (10 bits an
/// axis): neighbours in the order are neighbours in space.
fn morton_order(shapes: &[Shape], units: impl Iterator<Item = Unit> + Clone, count: usize) -> Vec<Unit> {
    use rayon::slice::ParallelSliceMut;
    let centre = |u: &Unit| Vec3::from(unit_bounds(shapes, u).center());
    let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for u in units.clone() {
        let c = centre(&u);
        (lo, hi) = (lo.min(c), hi.max(c));
    }
    let scale = 1023.0 / (hi - lo).max(Vec3::splat(f32::MIN_POSITIVE));
    let spread = |v: u32| {
        let mut x = v & 0x3ff;
        x = (x | x << 16) & 0x030000ff;
        x = (x | x << 8) & 0x0300f00f;
        x = (x | x << 4) & 0x030c30c3;
        (x | x << 2) & 0x09249249
    };
    let mut keyed: Vec<(u32, Unit)> = Vec::with_capacity(count);
    keyed.extend(units.map(|u| {
        let q = ((centre(&u) - lo) * scale).clamp(Vec3::ZERO, Vec3::splat(1023.0));
        (spread(q.x as u32) << 2 | spread(q.y as u32) << 1 | spread(q.z as u32), u)
    }));
    // A total order (units of equal code by shape and first index): the tree does not depend
    // on how the sort shares its work.
    keyed.par_sort_unstable_by_key(|k| (k.0, k.1.first.shape, k.1.first.index));
    keyed.into_iter().map(|k| k.1).collect()
}

/// The fibre segments among `members`' primitives, and whether they are at least half of
/// them: a tree mostly of fibres, which builds over pieces of them ([`PIECE`]).
fn fibre_share(shapes: &[Shape], members: &[u32]) -> (usize, bool) {
    let count: usize = members.iter().map(|&s| shapes[s as usize].prim_count()).sum();
    let fibres: usize = members
        .iter()
        .filter(|&&s| matches!(shapes[s as usize].geometry, Geometry::Curves(_)))
        .map(|&s| shapes[s as usize].prim_count())
        .sum();
    (fibres, 2 * fibres >= count)
}

/// The shapes of the top-level tree: those in no group.
fn top_level(shapes: &[Shape], groups: &[Vec<u32>]) -> Vec<u32> {
    let mut member = vec![false; shapes.len()];
    for &s in groups.iter().flatten() {
        member[s as usize] = true;
    }
    (0..shapes.len() as u32).filter(|&s| !member[s as usize]).collect()
}

/// What the builder takes as primitives for a tree over `members` ([`Unit`]): with `pieces`,
/// each fibre in pieces of up to [`PIECE`] joined segments; every other primitive alone.
fn units_of<'a>(
    shapes: &'a [Shape],
    members: &'a [u32],
    pieces: bool,
) -> impl Iterator<Item = Unit> + Clone + 'a {
    members.iter().flat_map(move |&s| {
        let shape = &shapes[s as usize];
        let (kind, fibre) = match &shape.geometry {
            Geometry::Mesh(_) => (TRIANGLE, None),
            Geometry::Curves(c) => (CURVE, Some(c).filter(|_| pieces)),
            _ => (0, None),
        };
        let n = shape.prim_count() as u32;
        let mut index = 0;
        std::iter::from_fn(move || {
            (index < n).then(|| {
                let mut len = 1;
                if let Some(c) = fibre {
                    while len < PIECE && c.joined_to_next((index + len - 1) as usize) {
                        len += 1;
                    }
                }
                let unit = Unit { first: PrimRef { shape: s | kind, index }, len };
                index += len;
                unit
            })
        })
    })
}

impl Accel {
    pub fn build(shapes: &[Shape]) -> Accel {
        Accel::build_grouped(shapes, &[])
    }

    /// The BVH of a scene with shape groups: `groups[g]` lists the shapes of group `g`, which
    /// get a tree of their own (in the group's space) and are left out of the top level,
    /// where each [`Instance`] of `g` is one primitive.
    ///
    /// # Panics
    /// If a group holds an instance, or an instance names no group in `groups`.
    pub fn build_grouped(shapes: &[Shape], groups: &[Vec<u32>]) -> Accel {
        Accel::build_in_batches(shapes, groups, BATCH)
    }

    /// How many primitives [`Accel::build_grouped`]'s builder would take for these shapes and
    /// groups, over all their trees ([`Unit`]: pieces of fibres in trees mostly of fibres), and
    /// the most in one tree: what its scratch memory follows.
    pub fn build_units(shapes: &[Shape], groups: &[Vec<u32>]) -> (usize, usize) {
        let top = top_level(shapes, groups);
        let counts: Vec<usize> = std::iter::once(&top)
            .chain(groups)
            .map(|m| units_of(shapes, m, fibre_share(shapes, m).1).count())
            .collect();
        (counts.iter().sum(), counts.iter().copied().max().unwrap_or(0))
    }

    /// [`Accel::build_grouped`] with bottom-level trees of at most `batch` primitives.
    fn build_in_batches(shapes: &[Shape], groups: &[Vec<u32>], batch: usize) -> Accel {
        for &s in groups.iter().flatten() {
            assert!(!matches!(shapes[s as usize].geometry, Geometry::Instance(_)), "nested instancing");
        }
        for s in shapes {
            if let Geometry::Instance(i) = &s.geometry {
                assert!(
                    (i.group as usize) < groups.len(),
                    "an instance of group {} of {}",
                    i.group,
                    groups.len()
                );
            }
        }
        let mut accel = Accel::build_over(shapes, &top_level(shapes, groups), batch);
        accel.groups = groups.iter().map(|g| Accel::build_over(shapes, g, batch)).collect();
        let nodes = accel.nodes.len() + accel.groups.iter().map(|g| g.nodes.len()).sum::<usize>();
        if nodes * std::mem::size_of::<FlatNode>() <= FLAT_BYTES {
            accel.set_flat(true);
        }
        accel
    }

    /// Whether the AVX2 kernel reads decoded planes ([`FlatNode`]) in this tree.
    pub fn flat_boxes(&self) -> bool {
        !self.flat.is_empty()
    }

    /// How this tree is traced, for the log: the kernel, and whether it reads the decoded
    /// planes (the same boxes either way, so the same images).
    pub fn describe(&self) -> String {
        let flat =
            if self.kernel == Kernel::Avx2 && self.flat_boxes() { ", boxes decoded to f32" } else { "" };
        format!("{}{flat}", self.kernel.name())
    }

    /// With or without the decoded planes, in this tree and its groups' (the build decides by
    /// size; tests trace both ways).
    fn set_flat(&mut self, on: bool) {
        self.flat = if on { self.nodes.iter().map(FlatNode::of).collect() } else { Vec::new() };
        for g in &mut self.groups {
            g.set_flat(on);
        }
    }

    /// The tree over the primitives of `shapes[members]`.
    fn build_over(shapes: &[Shape], members: &[u32], batch: usize) -> Accel {
        assert!(shapes.len() <= SHAPE as usize + 1, "{} shapes: a BVH names at most 2^29", shapes.len());
        let count: usize = members.iter().map(|&s| shapes[s as usize].prim_count()).sum();
        assert!(count <= MAX_PRIMS, "{count} primitives: one BVH holds at most {MAX_PRIMS}");
        let kernel = Kernel::detect();
        let (fibres, mostly_fibres) = fibre_share(shapes, members);
        let curves = fibres > 0;
        let units = || units_of(shapes, members, mostly_fibres);
        let mut b = Builder {
            shapes,
            pieces: mostly_fibres,
            nodes: vec![EMPTY_NODE],
            prims: Vec::with_capacity(count),
            tris: LeafTris::default(),
        };
        if count == 0 {
            return Accel {
                nodes: Vec::new(),
                flat: Vec::new(),
                prims: Vec::new(),
                tris: LeafTris::default(),
                stack_size: 0,
                kernel,
                curves,
                groups: Vec::new(),
                lone: 0,
                triangles: false,
            };
        }
        // Past two million primitives (a quarter of a million fibres), obvhs' better builds
        // cost more time than they save (docs/BENCHMARKS.md, "Fur at scale"). Below, a tree
        // mostly of fibres takes its slowest build (every node tried for reinsertion): render
        // instructions -5.4% on whimsical.xml, -2.7% on hair.xml, -4.6% on a generated fur of
        // 260k primitives, for about 3 us more a primitive of building (0.7 s there). Triangle
        // scenes keep the medium build: cbox -2%, but thinlens +3.8%.
        let mut params = if count > FAST_BUILD_ABOVE {
            BvhBuildParams::very_fast_build()
        } else if mostly_fibres {
            BvhBuildParams::very_slow_build()
        } else {
            BvhBuildParams::medium_build()
        };
        // Leaves of up to four primitives, collapsed where the SAH says a leaf is cheaper, with
        // a box test costing twice a primitive's. Leaves of 1 hold twice the nodes (29 bytes a
        // fibre segment against 16) and once rendered hair.xml 5% faster; measured again at
        // issue 15's twenty-fifth step, neither 1 nor 2 for fibre trees was faster on hair.xml or
        // whimsical.xml (docs/BENCHMARKS.md). 3 is 15% slower on cbox. A tree of fibre
        // pieces holds one piece a leaf; `merge_triangle_leaves` then joins its triangles.
        params.max_prims_per_leaf = if mostly_fibres { LEAF_MAX / PIECE } else { LEAF_MAX };
        params.collapse_traversal_cost = 2.0;
        let unit_count = units().count();
        let depth = if unit_count <= batch {
            let all: Vec<Unit> = units().collect();
            b.bottom(&all, params, 0).1
        } else {
            // Bounded batches: units in Morton order of their centres, a tree per BATCH of
            // them, and a tree over the batches. obvhs' scratch (about 300 bytes a unit) is
            // then held for one batch at a time.
            let order = morton_order(shapes, units(), unit_count);
            let mut roots = Vec::with_capacity(unit_count.div_ceil(batch));
            let mut depth = 0;
            for units in order.chunks(batch) {
                b.nodes.push(EMPTY_NODE);
                let slot = b.nodes.len() - 1;
                let (root_box, d) = b.bottom(units, params, slot);
                roots.push((slot as u32, root_box));
                depth = depth.max(d);
            }
            drop(order);
            let boxes: Vec<Aabb> = roots.iter().map(|r| r.1).collect();
            let mut top_params = BvhBuildParams::medium_build();
            top_params.max_prims_per_leaf = 1;
            let top = build_bvh2(&boxes, top_params, &mut Default::default());
            let top_depth = b.collapse(&top, 0, |leaf| {
                assert_eq!(leaf.prim_count, 1, "a top-level leaf holds one batch tree");
                roots[top.primitive_indices[leaf.first_index as usize] as usize].0
            });
            top_depth + depth
        };
        let Builder { mut nodes, prims, mut tris, .. } = b;
        let root = &nodes[0];
        let only = root.used.trailing_zeros() as usize;
        let lone = if nodes.len() == 1 && root.used.count_ones() == 1 && root.child[only] & LEAF != 0 {
            root.child[only]
        } else {
            0
        };
        tris.shrink_to_fit();
        nodes.shrink_to_fit();
        tracing::debug!(
            primitives = prims.len(),
            nodes = nodes.len(),
            depth,
            bytes = std::mem::size_of_val(nodes.as_slice())
                + std::mem::size_of_val(prims.as_slice())
                + tris.bytes(),
            "BVH built"
        );
        Accel {
            nodes,
            flat: Vec::new(),
            prims,
            tris,
            stack_size: (WIDTH - 1) * depth + 1,
            kernel,
            curves,
            groups: Vec::new(),
            lone,
            triangles: members.iter().any(|&s| matches!(shapes[s as usize].geometry, Geometry::Mesh(_))),
        }
    }

    pub fn prim_count(&self) -> usize {
        self.prims.len()
    }

    /// The kernel that tests boxes.
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// Uses `kernel` from now on (tests compare kernels; benchmarks time them).
    ///
    /// # Panics
    /// If this CPU cannot run it.
    pub fn set_kernel(&mut self, kernel: Kernel) {
        assert!(Kernel::available().contains(&kernel), "{kernel:?} is not available on this CPU");
        self.kernel = kernel;
        for g in &mut self.groups {
            g.set_kernel(kernel);
        }
    }

    /// The shape groups' trees: how many, and their primitives in all (each counted once,
    /// however many instances place it).
    pub fn group_stats(&self) -> (usize, usize) {
        (self.groups.len(), self.groups.iter().map(|g| g.prim_count()).sum())
    }

    /// Intersects the primitive leaves call `k` (a fibre segment has passed the leaf's quick
    /// miss test already).
    #[inline(always)]
    fn hit<const ANY: bool>(&self, q: &Query, k: usize, tmax: f32) -> Option<(f32, Vec2)> {
        let (ray, pre) = (q.ray, &q.pre);
        let prim = self.prims[k];
        if prim.shape & TRIANGLE != 0 {
            let [p0, p1, p2] = self.tris.vertices(prim.index as usize);
            intersect_triangle(ray, pre, tmax, p0, p1, p2).map(|(t, _, b1, b2)| (t, Vec2::new(b1, b2)))
        } else {
            let shape = &q.shapes[(prim.shape & SHAPE) as usize];
            match &shape.geometry {
                Geometry::Curves(c) => {
                    // (Inside an instance, `q.leaving` is the group's: `hit_instance`.)
                    let leaving = match q.leaving {
                        Some(l)
                            if l.segment == prim.index
                                && l.shape == prim.shape & SHAPE
                                && l.instance.is_none() =>
                        {
                            Some(l.piece)
                        }
                        _ => None,
                    };
                    c.intersect_exact(prim.index as usize, ray.o, ray.d, ray.tmin, tmax, leaving)
                        .map(|h| h.t_aux())
                }
                Geometry::Instance(inst) => self.hit_instance(q, inst, prim.shape & SHAPE, tmax, ANY),
                _ => shape.intersect(prim.index as usize, ray, pre, tmax),
            }
        }
    }

    /// The hit of `q`'s ray in instance `inst` (shape `index`) closer than `tmax` (any hit,
    /// with `any`): its world distance, and the hit itself in `q.inner`. A ray leaving a fibre
    /// piece of this instance skips that piece in the group's tree; in other instances the
    /// piece is another surface.
    #[inline(never)]
    fn hit_instance(
        &self,
        q: &Query,
        inst: &Instance,
        index: u32,
        tmax: f32,
        any: bool,
    ) -> Option<(f32, Vec2)> {
        let local = inst.local_ray(q.ray, tmax);
        if !(local.ray.tmax > local.ray.tmin) {
            return None;
        }
        let leaving =
            q.leaving.filter(|l| l.instance == Some(index)).map(|l| Leaving { instance: None, ..l });
        let group = &self.groups[inst.group as usize];
        let mut inner = Query::from(q.shapes, &local.ray, SpawnedFrom::piece(leaving), group.triangles);
        let (t, k, aux) = group.query_with(&mut inner, any)?;
        let world = (t + local.shift) / local.scale;
        if !(world < tmax) {
            return None;
        }
        q.inner.set((k, aux, t));
        Some((world, Vec2::ZERO))
    }

    /// The closest hit of `ray` (any hit, with `any`): its distance, leaf-order primitive and
    /// aux values, with what an instance's hit left in `q.inner`.
    #[inline(always)]
    fn query_with<'a>(&self, q: &mut Query<'a>, any: bool) -> Option<(f32, u32, Vec2)> {
        if self.nodes.is_empty() {
            return None;
        }
        // SAFETY: `self.kernel` is one that this CPU runs (`detect`, `set_kernel`).
        let t = unsafe {
            match (self.kernel, any) {
                #[cfg(target_arch = "x86_64")]
                (Kernel::Avx2, false) => self.closest_avx(q),
                #[cfg(target_arch = "x86_64")]
                (Kernel::Avx2, true) => self.any_avx(q),
                #[cfg(target_arch = "x86_64")]
                (Kernel::Sse, false) => self.traverse::<SseTest, false>(q),
                #[cfg(target_arch = "x86_64")]
                (Kernel::Sse, true) => self.traverse::<SseTest, true>(q),
                (_, false) => self.traverse::<ScalarTest, false>(q),
                (_, true) => self.traverse::<ScalarTest, true>(q),
            }
        };
        // (aux read a coordinate at a time, as the traversal stored it: `math::apart2`.)
        q.best.map(|(k, aux)| (t, k, crate::math::apart2(aux)))
    }

    /// The interaction of the hit at `t` on the primitive leaves call `k`.
    fn interaction(
        &self,
        shapes: &[Shape],
        k: u32,
        ray: &Ray,
        t: f32,
        aux: Vec2,
        inner: (u32, Vec2, f32),
    ) -> Interaction {
        let prim = self.prims[k as usize];
        let shape = prim.shape & SHAPE;
        if prim.shape & (TRIANGLE | CURVE) == 0 {
            if let Geometry::Instance(inst) = &shapes[shape as usize].geometry {
                return self.instance_interaction(shapes, inst, shape, ray, t, inner);
            }
        }
        let index =
            if prim.shape & TRIANGLE != 0 { self.tris.mesh_index(prim.index as usize) } else { prim.index };
        shapes[shape as usize].interaction(shape, index as usize, ray, t, aux)
    }

    /// The interaction of a hit inside instance `inst` (shape `index`; at world distance `t`;
    /// `inner` as [`Query::inner`] left it), in world space.
    #[cold]
    #[inline(never)]
    fn instance_interaction(
        &self,
        shapes: &[Shape],
        inst: &Instance,
        index: u32,
        ray: &Ray,
        t: f32,
        inner: (u32, Vec2, f32),
    ) -> Interaction {
        let (k, aux, t_local) = inner;
        // The traversal's local ray (its far end aside, which the interaction does not read).
        let local = inst.local_ray(ray, ray.tmax);
        let group = &self.groups[inst.group as usize];
        inst.to_world(&group.interaction(shapes, k, &local.ray, t_local, aux, inner), t, index)
    }

    /// The centres (coordinate by coordinate) and radii squared of the `count` primitives from
    /// `first`, if all are balls; `None` otherwise.
    #[inline(always)]
    fn leaf_balls(&self, shapes: &[Shape], first: u32, count: u32) -> Option<([[f32; 4]; 3], [f32; 4])> {
        let (mut c, mut rr) = ([[0.0f32; 4]; 3], [0.0f32; 4]);
        for j in 0..count as usize {
            // SAFETY: a leaf's primitives are in `prims`.
            let prim = unsafe { self.prims.get_unchecked(first as usize + j) };
            if prim.shape & (TRIANGLE | CURVE) != 0 {
                return None;
            }
            let Geometry::Sphere(ball) = &shapes[(prim.shape & SHAPE) as usize].geometry else { return None };
            for (a, c) in c.iter_mut().enumerate() {
                c[j] = ball.center[a];
            }
            // (As `intersect_sphere` squares it.)
            rr[j] = ball.radius * ball.radius;
        }
        Some((c, rr))
    }

    /// Which of a leaf's primitives are fibre segments that the ray certainly misses (bit `j`
    /// for the leaf's `j`-th), all tested together.
    #[inline(always)]
    fn curve_misses(&self, q: &Query, first: u32, count: u32) -> u32 {
        const _: () = assert!(LEAF_MAX <= 4, "missed_by4 tests four segments");
        let mut lanes: [Option<&Segment>; 4] = [None; 4];
        let mut curves = 0u32;
        for j in 0..count as usize {
            let prim = self.prims[first as usize + j];
            if prim.shape & CURVE != 0 {
                if let Geometry::Curves(c) = &q.shapes[(prim.shape & SHAPE) as usize].geometry {
                    lanes[j] = Some(&c.segments[prim.index as usize]);
                    curves |= 1 << j;
                }
            }
        }
        if curves == 0 {
            return 0;
        }
        let any = lanes[curves.trailing_zeros() as usize].unwrap_or_else(|| unreachable!());
        missed_by4(q.ray.o, q.ray.d, &Segments4::gather(lanes.map(|s| s.unwrap_or(any)))) & curves
    }

    /// The closest hit along `ray`, if any.
    pub fn intersect(&self, shapes: &[Shape], ray: &Ray) -> Option<Interaction> {
        let hit = self.closest(shapes, ray, SpawnedFrom::NOTHING)?;
        Some(self.hit_interaction(shapes, ray, &hit))
    }

    /// The closest hit along `ray`, if any, before its interaction is made
    /// ([`Accel::hit_interaction`]). A caller that makes it only after testing for a miss
    /// builds it where it is used; made inside an `Option`, its fields were written in
    /// pieces and copied out whole, and the copy waited on those writes (a failed store
    /// forward).
    /// `from`: what the ray was spawned from ([`Accel::spawned_from`]), which is not tested
    /// (it has no hit to give the ray).
    #[inline]
    pub fn closest(&self, shapes: &[Shape], ray: &Ray, from: SpawnedFrom) -> Option<Hit> {
        #[cfg(feature = "ray-log")]
        ray_log::note(ray, from, false);
        if from.leaf != 0 && from.leaf == self.lone {
            return None;
        }
        let mut q = Query::from(shapes, ray, from, self.triangles);
        let (t, k, aux) = self.query_with(&mut q, false)?;
        Some(Hit { t, k, aux, inner: q.inner.get(), leaf: q.leaf })
    }

    /// Whether anything blocks `ray` within `[tmin, tmax)`.
    pub fn occluded(&self, shapes: &[Shape], ray: &Ray) -> bool {
        self.occluded_from(shapes, ray, SpawnedFrom::NOTHING)
    }

    /// [`Accel::occluded`] for a ray spawned from `from` ([`Accel::spawned_from`]).
    pub fn occluded_from(&self, shapes: &[Shape], ray: &Ray, from: SpawnedFrom) -> bool {
        #[cfg(feature = "ray-log")]
        ray_log::note(ray, from, true);
        if from.leaf != 0 && from.leaf == self.lone {
            return false;
        }
        self.query_with(&mut Query::from(shapes, ray, from, self.triangles), true).is_some()
    }

    /// What a ray spawned at `hit` (whose interaction is `it`) along `d` leaves behind, for
    /// [`Accel::closest`] and [`Accel::occluded_from`] to pass over: the fibre piece it leaves
    /// ([`Leaving`]), and the hit's leaf where the ray cannot meet that leaf again. That is a
    /// leaf of triangles in one plane (a rectangle: `PLANAR`) or a disk, whichever way the
    /// ray goes, and a sphere alone in its leaf when the ray heads out of it (the line then
    /// meets the sphere only behind its start). All such a leaf could give the ray is a hit on
    /// itself where it starts, which the spawn offset is there to avoid (and, in a leaf flat
    /// only to within `FLAT`, a hit on a neighbour for a ray leaving within about `FLAT`
    /// radians of the plane); the test it no longer takes is often the query's first, as the
    /// ray starts inside the leaf's box.
    #[inline]
    pub fn spawned_from(&self, shapes: &[Shape], hit: &Hit, it: &Interaction, d: Vec3) -> SpawnedFrom {
        let piece = it.leaving();
        let leaf = hit.leaf;
        if leaf & LEAF == 0 {
            return SpawnedFrom { piece, leaf: 0 };
        }
        let first = self.prims[(leaf & FIRST) as usize];
        let own = if first.shape & PLANAR != 0 {
            true
        } else if leaf & (TRI_LEAF | COUNT) == 0 && first.shape & (TRIANGLE | CURVE) == 0 {
            let shape = &shapes[(first.shape & SHAPE) as usize];
            match shape.geometry {
                Geometry::Disk(_) => true,
                // (The geometric normal, unflipped, points out of the ball.)
                Geometry::Sphere(_) => (if shape.flip_normals { -it.ng } else { it.ng }).dot(d) > 0.0,
                _ => false,
            }
        } else {
            false
        };
        SpawnedFrom { piece, leaf: if own { leaf } else { 0 } }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn closest_avx(&self, q: &mut Query) -> f32 {
        debug_assert!(self.flat.is_empty() || self.flat.len() == self.nodes.len());
        if self.flat.is_empty() {
            self.traverse::<AvxTest, false>(q)
        } else {
            self.traverse::<AvxFlatTest, false>(q)
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn any_avx(&self, q: &mut Query) -> f32 {
        debug_assert!(self.flat.is_empty() || self.flat.len() == self.nodes.len());
        if self.flat.is_empty() {
            self.traverse::<AvxTest, true>(q)
        } else {
            self.traverse::<AvxFlatTest, true>(q)
        }
    }

    /// Walks the tree for `q`: the closest hit (`ANY` false) or any hit (`ANY` true) goes to
    /// `q.best`; returns its distance.
    ///
    /// # Safety
    /// The CPU must run `T`'s instructions.
    #[inline(always)]
    unsafe fn traverse<T: BoxTest, const ANY: bool>(&self, q: &mut Query) -> f32 {
        let r = BoxRay::new(q.ray);
        let tri_ray = TriRay::new(q.ray, &q.pre);
        let mut hits = MaybeUninit::<QuadHits>::uninit();
        let tmin = q.ray.tmin;
        let mut tmax = q.ray.tmax;
        let mut inline = [MaybeUninit::<(u32, f32)>::uninit(); INLINE_STACK];
        let mut heap;
        let stack: &mut [MaybeUninit<(u32, f32)>] = if self.stack_size <= INLINE_STACK {
            &mut inline
        } else {
            heap = deep_stack(self.stack_size);
            &mut heap
        };
        let mut sp = 0;
        let mut cur = 0u32; // the root
        loop {
            if cur & LEAF != 0 {
                if cur != q.skip && self.test_leaf::<T, ANY>(q, cur, &tri_ray, tmin, &mut tmax, &mut hits) {
                    return tmax;
                }
            } else {
                let (mut mask, tn, child) = if T::FLAT {
                    let node = self.flat.get_unchecked(cur as usize);
                    let (mask, tn) = T::test_flat(node, &r, tmin, tmax);
                    (mask, tn, &node.child)
                } else {
                    let node = self.nodes.get_unchecked(cur as usize);
                    let (mask, tn) = T::test(node, &r, tmin, tmax);
                    (mask, tn, &node.child)
                };
                if mask != 0 {
                    let lane = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    if mask == 0 {
                        cur = child[lane];
                        continue;
                    }
                    // Two or more children: push all but the nearest, farthest deepest.
                    let base = sp;
                    let mut nearest = (child[lane], tn[lane]);
                    while mask != 0 {
                        let lane = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        let mut e = (child[lane], tn[lane]);
                        if !ANY && e.1 < nearest.1 {
                            std::mem::swap(&mut e, &mut nearest);
                        }
                        // Insertion into the pushed run, kept in decreasing distance.
                        let mut i = sp;
                        if !ANY {
                            while i > base && stack[i - 1].assume_init().1 < e.1 {
                                stack[i] = stack[i - 1];
                                i -= 1;
                            }
                        }
                        stack[i] = MaybeUninit::new(e);
                        sp += 1;
                    }
                    cur = nearest.0;
                    continue;
                }
            }
            // Pop the nearest pending child that may still hold a closer hit.
            loop {
                if sp == 0 {
                    return tmax;
                }
                sp -= 1;
                let (c, t) = stack[sp].assume_init();
                // The box test's own slack: a child that passed it is never dropped here.
                if t <= tmax * FAR_SCALE {
                    cur = c;
                    break;
                }
            }
        }
    }

    /// Tests the primitives of leaf `cur` against `q`'s ray, updating `tmax` and `q.best` with
    /// every closer hit; true once a hit is found, if `ANY` (a shadow ray is then done).
    ///
    /// # Safety
    /// The CPU must run `T`'s instructions; `cur` must be a leaf of this tree.
    #[inline(always)]
    unsafe fn test_leaf<T: BoxTest, const ANY: bool>(
        &self,
        q: &mut Query,
        cur: u32,
        tri_ray: &TriRay,
        tmin: f32,
        tmax: &mut f32,
        hits: &mut MaybeUninit<QuadHits>,
    ) -> bool {
        let first = cur & ((1 << FIRST_BITS) - 1);
        let count = ((cur >> FIRST_BITS) & 3) + 1;
        // A leaf of triangles is tested together (x86 kernels), unless a lane's ray
        // passes exactly through an edge; the lanes that hit are then taken in order,
        // each against the closest hit so far, as the loop over primitives would.
        #[cfg(target_arch = "x86_64")]
        let quad = if T::QUADS && cur & TRI_LEAF != 0 {
            let slot0 = self.prims.get_unchecked(first as usize).index as usize;
            // SAFETY: the leaf's block, and at least three floats after it.
            let block = self.tris.data.as_ptr().add(9 * slot0);
            x86::quad_sse(block, count as usize, tri_ray, tmin, *tmax, hits)
        } else {
            None
        };
        #[cfg(not(target_arch = "x86_64"))]
        let quad: Option<u32> = {
            let _ = (tri_ray, &hits); // no 4-lane test here: one at a time
            None
        };
        if let Some(mut mask) = quad {
            if mask != 0 {
                // SAFETY: `quad` wrote `hits`, as some lane hit.
                let h = hits.assume_init_ref();
                while mask != 0 {
                    let j = mask.trailing_zeros() as usize;
                    mask &= mask - 1;
                    if h.within(j, *tmax) && h.t[j] < *tmax {
                        *tmax = h.t[j];
                        q.best = Some((first + j as u32, Vec2::new(h.b1[j], h.b2[j])));
                        q.leaf = cur;
                        if ANY {
                            return true;
                        }
                    }
                }
            }
        } else {
            // A leaf of two or more balls alone (x86 kernels): tested together, then taken in
            // order, each against the closest hit so far, as the loop below would.
            #[cfg(target_arch = "x86_64")]
            if T::QUADS && count > 1 {
                if let Some((c, rr)) = self.leaf_balls(q.shapes, first, count) {
                    let (mut mask, t) = x86::balls_sse(q.ray, &c, rr, (1 << count) - 1, *tmax);
                    while mask != 0 {
                        let j = mask.trailing_zeros();
                        mask &= mask - 1;
                        // (A lane's nearer root past a closer hit leaves its farther one past it
                        // too: the same as `intersect_sphere` against that hit.)
                        if t[j as usize] < *tmax {
                            *tmax = t[j as usize];
                            q.best = Some((first + j, Vec2::ZERO));
                            q.leaf = cur;
                            if ANY {
                                return true;
                            }
                        }
                    }
                    return false;
                }
            }
            let skip = if self.curves { self.curve_misses(q, first, count) } else { 0 };
            for (j, k) in (first..first + count).enumerate() {
                if skip >> j & 1 != 0 {
                    continue;
                }
                if let Some((t, aux)) = self.hit::<ANY>(q, k as usize, *tmax) {
                    if t < *tmax {
                        *tmax = t;
                        q.best = Some((k, aux));
                        q.leaf = cur;
                        if ANY {
                            return true;
                        }
                    }
                }
            }
        }
        false
    }

    /// (Crate-private, as are [`Accel::intersect_among`] and [`Accel::intersect_among_packet`]:
    /// those read the gathered leaves unchecked, so they must come from this tree.)
    ///
    /// Gathers into `out` the leaves whose boxes `bundle` may meet, nearest first by a lower
    /// bound of the distance along any of its rays; gives up (`out.complete` false) past
    /// [`MAX_CANDIDATES`] leaves or [`MAX_BUNDLE_NODES`] nodes, where tracing each ray through
    /// the tree is cheaper. Which leaves, and their order, depend only on the bundle (every
    /// kernel computes the same IEEE operations).
    pub(crate) fn gather(&self, bundle: &Bundle, out: &mut Candidates) {
        // SAFETY: `self.kernel` is one that this CPU runs (`detect`, `set_kernel`).
        #[cfg(target_arch = "x86_64")]
        if self.kernel == Kernel::Avx2 {
            unsafe { self.gather_avx(bundle, out) };
            return;
        }
        self.gather_with(out, |node| bundle_test_scalar(node, bundle));
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn gather_avx(&self, bundle: &Bundle, out: &mut Candidates) {
        self.gather_with(out, |node| x86::bundle_test_avx2(node, bundle));
    }

    /// [`Accel::gather`] with `test` telling which of a node's children the bundle meets and
    /// how near.
    #[inline(always)]
    fn gather_with(&self, out: &mut Candidates, test: impl Fn(&Node) -> (u32, [f32; WIDTH])) {
        out.leaves.clear();
        out.complete = false;
        if self.nodes.is_empty() {
            out.complete = true;
            return;
        }
        let mut stack = [0u32; MAX_BUNDLE_NODES];
        let (mut sp, mut visited) = (1, 0);
        while sp > 0 {
            sp -= 1;
            visited += 1;
            let node = &self.nodes[stack[sp] as usize];
            let (mut mask, near) = test(node);
            while mask != 0 {
                let i = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let child = node.child[i];
                if child & LEAF != 0 {
                    if out.leaves.len() == MAX_CANDIDATES {
                        return;
                    }
                    out.leaves.push((near[i], child));
                } else {
                    if visited + sp >= MAX_BUNDLE_NODES {
                        return;
                    }
                    stack[sp] = child;
                    sp += 1;
                }
            }
        }
        out.leaves.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        out.complete = true;
    }

    /// The closest hit along `ray`, a ray of the bundle that `cands` was gathered for
    /// ([`Accel::gather`]): only its leaves are tested, nearest first, until the next one
    /// lies past the closest hit. The same hit as [`Accel::intersect`] (up to which of two
    /// primitives at exactly the same distance is reported). The packets' reference in tests.
    #[cfg(test)]
    pub(crate) fn intersect_among(
        &self,
        shapes: &[Shape],
        ray: &Ray,
        cands: &Candidates,
    ) -> Option<Interaction> {
        let hit = self.among_hit(shapes, ray, cands)?;
        Some(self.hit_interaction(shapes, ray, &hit))
    }

    /// [`Accel::intersect_among`]'s hit, before its interaction is made.
    fn among_hit(&self, shapes: &[Shape], ray: &Ray, cands: &Candidates) -> Option<Hit> {
        let mut q = Query::new(shapes, ray);
        if !cands.complete {
            let (t, k, aux) = self.query_with(&mut q, false)?;
            return Some(Hit { t, k, aux, inner: q.inner.get(), leaf: q.leaf });
        }
        // SAFETY: `self.kernel` is one that this CPU runs (`detect`, `set_kernel`).
        let t = unsafe {
            match self.kernel {
                #[cfg(target_arch = "x86_64")]
                Kernel::Avx2 => self.among_avx(&mut q, &cands.leaves),
                #[cfg(target_arch = "x86_64")]
                Kernel::Sse => self.among::<SseTest>(&mut q, &cands.leaves),
                _ => self.among::<ScalarTest>(&mut q, &cands.leaves),
            }
        };
        let (k, aux) = q.best?;
        Some(Hit { t, k, aux, inner: q.inner.get(), leaf: q.leaf })
    }

    /// The interaction of `hit`, found along `ray`.
    pub fn hit_interaction(&self, shapes: &[Shape], ray: &Ray, hit: &Hit) -> Interaction {
        self.interaction(shapes, hit.k, ray, hit.t, hit.aux, hit.inner)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn among_avx(&self, q: &mut Query, leaves: &[(f32, u32)]) -> f32 {
        self.among::<AvxTest>(q, leaves)
    }

    /// Tests `leaves` (nearest first) against `q`'s ray until the next lies past the closest
    /// hit; returns its distance.
    ///
    /// # Safety
    /// The CPU must run `T`'s instructions; `leaves` must be leaves of this tree.
    #[inline(always)]
    unsafe fn among<T: BoxTest>(&self, q: &mut Query, leaves: &[(f32, u32)]) -> f32 {
        let tri_ray = TriRay::new(q.ray, &q.pre);
        let mut hits = MaybeUninit::<QuadHits>::uninit();
        let tmin = q.ray.tmin;
        let mut tmax = q.ray.tmax;
        for &(near, leaf) in leaves {
            if near > tmax {
                break;
            }
            self.test_leaf::<T, false>(q, leaf, &tri_ray, tmin, &mut tmax, &mut hits);
        }
        tmax
    }
}

/// The rays traced through [`Accel::closest`] and [`Accel::occluded_from`] while logging is
/// on, to be traced again alone (`core/benches/traversal_share.rs`: how much of a render's
/// time its traversals take). Built only with the `ray-log` feature.
#[cfg(feature = "ray-log")]
pub mod ray_log {
    use super::{Ray, SpawnedFrom};
    use std::sync::atomic::{AtomicBool, Ordering::Relaxed};
    use std::sync::Mutex;

    /// A logged query: the ray, what it leaves, and whether it was a shadow ray's.
    pub type Query = (Ray, SpawnedFrom, bool);

    static ON: AtomicBool = AtomicBool::new(false);
    static LOG: Mutex<Vec<Query>> = Mutex::new(Vec::new());

    pub(super) fn note(ray: &Ray, from: SpawnedFrom, any: bool) {
        if ON.load(Relaxed) {
            LOG.lock().unwrap_or_else(|e| e.into_inner()).push((*ray, from, any));
        }
    }

    /// The queries traced while `f` runs (on any thread).
    pub fn during(f: impl FnOnce()) -> Vec<Query> {
        LOG.lock().unwrap_or_else(|e| e.into_inner()).clear();
        ON.store(true, Relaxed);
        f();
        ON.store(false, Relaxed);
        std::mem::take(&mut *LOG.lock().unwrap_or_else(|e| e.into_inner()))
    }
}

/// What a ray spawned from a surface leaves behind, which its traversal passes over: the
/// fibre piece ([`Leaving`]) and a leaf that it cannot meet again ([`Accel::spawned_from`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SpawnedFrom {
    pub piece: Option<Leaving>,
    /// A leaf reference of the tree whose [`Accel::spawned_from`] made it; 0 for none.
    leaf: u32,
}

impl SpawnedFrom {
    /// A ray from nowhere (a camera's): every primitive is tested.
    pub const NOTHING: SpawnedFrom = SpawnedFrom { piece: None, leaf: 0 };

    /// A ray that leaves the fibre piece `piece` (if any) and nothing else.
    pub fn piece(piece: Option<Leaving>) -> SpawnedFrom {
        SpawnedFrom { piece, leaf: 0 }
    }
}

/// Camera rays of one pixel traced together by [`Accel::intersect_among_packet`].
pub const PACKET: usize = 8;

/// A closest hit before its interaction is made ([`Accel::hit_interaction`]): 36 bytes where
/// the interaction takes 128.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    t: f32,
    /// The leaf-order primitive and its aux values.
    k: u32,
    aux: Vec2,
    /// [`Query::inner`], for a hit inside an instance.
    inner: (u32, Vec2, f32),
    /// The leaf that holds primitive `k` (for [`Accel::spawned_from`]).
    leaf: u32,
}

impl Hit {
    /// The distance along the ray.
    pub fn distance(&self) -> f32 {
        self.t
    }
}

impl Accel {
    /// [`Accel::intersect_among`] for each of `rays` (at most [`PACKET`], all of the bundle
    /// `cands` was gathered for), into `out` ([`Accel::hit_interaction`] makes a hit's
    /// interaction): the same hits, bit for bit. With the AVX2 kernel,
    /// where the rays share the triangle test's axes ([`RayPre`]), a leaf's triangles are
    /// tested against all the rays at once, one ray a lane, each ray through the leaves its own
    /// query would test (it stops at the first leaf beyond its closest hit) and each lane
    /// computing what [`intersect_triangle`] computes for its ray; other leaves are tested ray
    /// by ray as [`Accel::intersect_among`] tests them.
    ///
    /// # Panics
    /// If `rays` is longer than [`PACKET`] or `out` is not as long as `rays`.
    pub(crate) fn intersect_among_packet(
        &self,
        shapes: &[Shape],
        rays: &[Ray],
        cands: &Candidates,
        out: &mut [Option<Hit>],
    ) {
        assert!(rays.len() <= PACKET && out.len() == rays.len(), "{} rays into {}", rays.len(), out.len());
        if cands.complete && cands.leaves.is_empty() {
            // The pixel's bundle meets no leaf (a sky pixel): every ray escapes, and nothing
            // need be set up to find that out.
            out.fill(None);
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if cands.complete && self.kernel == Kernel::Avx2 && rays.len() > 1 {
            let n = rays.len();
            // Lanes past `n` repeat the last ray; they are never tested.
            let last = Query::new(shapes, &rays[n - 1]);
            // Copies of `last`, the others then aimed along their rays: a query made whole for
            // each lane was built aside and copied in (a `memcpy` call per packet in the
            // profile-guided build).
            let mut qs: [Query; PACKET] = std::array::from_fn(|_| last.clone());
            for (q, ray) in qs.iter_mut().zip(&rays[..n - 1]) {
                q.aim(ray);
            }
            let p = &qs[0].pre;
            if qs[1..n].iter().all(|q| (q.pre.kx, q.pre.ky, q.pre.kz) == (p.kx, p.ky, p.kz)) {
                // SAFETY: the AVX2 kernel is only chosen where the CPU runs it (`detect`,
                // `set_kernel`); `leaves` are leaves of this tree.
                let tmax = unsafe { self.among_packet_avx(&mut qs, n, &cands.leaves) };
                for (j, o) in out.iter_mut().enumerate() {
                    let q = &qs[j];
                    *o =
                        q.best.map(|(k, aux)| Hit { t: tmax[j], k, aux, inner: q.inner.get(), leaf: q.leaf });
                }
                return;
            }
        }
        for (ray, o) in rays.iter().zip(out) {
            *o = self.among_hit(shapes, ray, cands);
        }
    }

    /// [`Accel::among`] for the first `n` of eight queries whose rays share their [`RayPre`]
    /// axes: each query's closest hit goes to its `best`; returns their distances.
    ///
    /// # Safety
    /// The CPU must run AVX2; `leaves` must be leaves of this tree.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn among_packet_avx(
        &self,
        qs: &mut [Query; PACKET],
        n: usize,
        leaves: &[(f32, u32)],
    ) -> [f32; PACKET] {
        use std::arch::x86_64::*;
        let shapes = qs[0].shapes;
        let rays: [&Ray; PACKET] = std::array::from_fn(|j| qs[j].ray);
        macro_rules! lanes {
            (|$r:ident| $e:expr) => {{
                let a: [f32; PACKET] = std::array::from_fn(|j| {
                    let $r = rays[j];
                    $e
                });
                _mm256_loadu_ps(a.as_ptr())
            }};
        }
        let mut tmax: [f32; PACKET] = std::array::from_fn(|j| rays[j].tmax);
        let tmin: [f32; PACKET] = std::array::from_fn(|j| rays[j].tmin);
        let (kx, ky, kz) = (qs[0].pre.kx, qs[0].pre.ky, qs[0].pre.kz);
        macro_rules! shear {
            ($s:ident) => {{
                let a: [f32; PACKET] = std::array::from_fn(|j| qs[j].pre.$s);
                _mm256_loadu_ps(a.as_ptr())
            }};
        }
        let ray = TriRayLanes {
            o: [lanes!(|r| r.o[kx]), lanes!(|r| r.o[ky]), lanes!(|r| r.o[kz])],
            s: [shear!(sx), shear!(sy), shear!(sz)],
            tmin: _mm256_loadu_ps(tmin.as_ptr()),
        };
        let mut tmax_v = _mm256_loadu_ps(tmax.as_ptr());
        let mut rays_xyz: Option<SphereRayLanes> = None;
        let mut hits = MaybeUninit::<QuadHits>::uninit();
        // The rays still testing leaves: a ray's own query stops at the first leaf that lies
        // past its closest hit.
        let mut alive = (1u32 << n) - 1;
        for &(near, leaf) in leaves {
            let on = _mm256_cmp_ps::<_CMP_NGT_UQ>(_mm256_set1_ps(near), tmax_v);
            alive &= _mm256_movemask_ps(on) as u32;
            if alive == 0 {
                break;
            }
            let first = leaf & ((1 << FIRST_BITS) - 1);
            let count = ((leaf >> FIRST_BITS) & 3) as usize + 1;
            if leaf & TRI_LEAF == 0 {
                // A leaf of spheres: each against all the rays at once.
                let sphere = |j: usize| {
                    let prim = self.prims.get_unchecked(first as usize + j);
                    match &shapes[(prim.shape & SHAPE) as usize].geometry {
                        Geometry::Sphere(s) if prim.shape & (TRIANGLE | CURVE) == 0 => Some(s),
                        _ => None,
                    }
                };
                if (0..count).all(|j| sphere(j).is_some()) {
                    let d = rays_xyz.get_or_insert_with(|| SphereRayLanes {
                        o: [lanes!(|r| r.o.x), lanes!(|r| r.o.y), lanes!(|r| r.o.z)],
                        d: [lanes!(|r| r.d.x), lanes!(|r| r.d.y), lanes!(|r| r.d.z)],
                        tmin: ray.tmin,
                    });
                    for j in 0..count {
                        let Some(ball) = sphere(j) else { continue };
                        let (mut accept, t) = x86::sphere_lanes(d, ball, tmax_v, alive);
                        while accept != 0 {
                            let lane = accept.trailing_zeros() as usize;
                            accept &= accept - 1;
                            tmax[lane] = t[lane];
                            qs[lane].best = Some((first + j as u32, Vec2::ZERO));
                            qs[lane].leaf = leaf;
                        }
                        tmax_v = _mm256_loadu_ps(tmax.as_ptr());
                    }
                    continue;
                }
                let mut live = alive;
                while live != 0 {
                    let j = live.trailing_zeros() as usize;
                    live &= live - 1;
                    let tri_ray = TriRay::new(qs[j].ray, &qs[j].pre);
                    self.test_leaf::<AvxTest, false>(
                        &mut qs[j],
                        leaf,
                        &tri_ray,
                        tmin[j],
                        &mut tmax[j],
                        &mut hits,
                    );
                }
                tmax_v = _mm256_loadu_ps(tmax.as_ptr());
                continue;
            }
            let slot0 = self.prims.get_unchecked(first as usize).index as usize;
            // SAFETY: the leaf's block of `count` triangles ([`LeafTris`]).
            let block = self.tris.data.as_ptr().add(9 * slot0);
            for tri in 0..count {
                macro_rules! vertex {
                    ($v:expr) => {
                        [kx, ky, kz].map(|a| *block.add((3 * $v + a) * count + tri))
                    };
                }
                let (accept, edge, t, b1, b2) =
                    x86::tri_lanes(&ray, [vertex!(0), vertex!(1), vertex!(2)], tmax_v, alive);
                let k = first + tri as u32;
                let mut m = accept;
                while m != 0 {
                    let j = m.trailing_zeros() as usize;
                    m &= m - 1;
                    tmax[j] = t[j];
                    qs[j].best = Some((k, Vec2::new(b1[j], b2[j])));
                    qs[j].leaf = leaf;
                }
                // A ray through an edge exactly: the scalar test (double precision there).
                let mut m = edge;
                while m != 0 {
                    let j = m.trailing_zeros() as usize;
                    m &= m - 1;
                    let [p0, p1, p2] = self.tris.vertices(slot0 + tri);
                    let q = &mut qs[j];
                    if let Some((t, _, b1, b2)) = intersect_triangle(q.ray, &q.pre, tmax[j], p0, p1, p2) {
                        if t < tmax[j] {
                            tmax[j] = t;
                            q.best = Some((k, Vec2::new(b1, b2)));
                            q.leaf = leaf;
                        }
                    }
                }
                if accept | edge != 0 {
                    tmax_v = _mm256_loadu_ps(tmax.as_ptr());
                }
            }
        }
        tmax
    }
}

/// Eight rays for [`x86::sphere_lanes`], one a lane: origins, directions and near ends.
#[cfg(target_arch = "x86_64")]
struct SphereRayLanes {
    o: [std::arch::x86_64::__m256; 3],
    d: [std::arch::x86_64::__m256; 3],
    tmin: std::arch::x86_64::__m256,
}

/// Eight rays' constants for [`x86::tri_lanes`], one ray a lane: origins and shears on the
/// axes their (shared) [`RayPre`] permutes to x, y and z, and near ends.
#[cfg(target_arch = "x86_64")]
struct TriRayLanes {
    o: [std::arch::x86_64::__m256; 3],
    s: [std::arch::x86_64::__m256; 3],
    tmin: std::arch::x86_64::__m256,
}

/// Most leaves [`Accel::gather`] keeps for one bundle.
const MAX_CANDIDATES: usize = 16;
/// Most nodes [`Accel::gather`] visits (or holds pending) for one bundle.
const MAX_BUNDLE_NODES: usize = 16;

/// A bundle of rays: every ray whose origin lies within `radius` of `origin` and whose points
/// p stay on the inner side (`n . (p - origin) + c >= 0`) of `planes[8]` and, for each of
/// four sides, of at least one of the side's two planes (`planes[2 s]`, `planes[2 s + 1]`).
/// Relative to `origin`, so that f32 keeps the planes' precision near it. A pixel's camera
/// rays, pinhole or thin lens, form one ([`crate::camera::PixelBundles::pixel`]).
#[derive(Clone, Debug)]
pub struct Bundle {
    pub planes: [([f32; 3], f32); 9],
    pub origin: [f32; 3],
    pub radius: f32,
}

/// The leaves of one bundle, nearest first ([`Accel::gather`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Candidates {
    leaves: Vec<(f32, u32)>,
    /// Whether `leaves` holds every leaf the bundle meets (else rays are traced whole).
    complete: bool,
}

impl Candidates {
    /// How many leaves, if the gathering was complete.
    pub fn len(&self) -> Option<usize> {
        self.complete.then_some(self.leaves.len())
    }
}

/// A traversal stack for trees deeper than the inline one serves (out of the hot path).
#[cold]
#[inline(never)]
fn deep_stack(size: usize) -> Vec<MaybeUninit<(u32, f32)>> {
    vec![MaybeUninit::uninit(); size]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Mesh;

    fn xorshift(s: &mut u64) -> f32 {
        *s ^= *s << 13;
        *s ^= *s >> 7;
        *s ^= *s << 17;
        (*s >> 40) as f32 / (1u64 << 24) as f32
    }

    /// The wide nodes a collapse makes (the binary nodes it opens), from the root; checks that
    /// each has 2 to WIDTH children and that every leaf is some wide node's child exactly once.
    fn opened(b2: &[obvhs::bvh2::node::Bvh2Node], plan: &SlotPlan) -> Vec<usize> {
        let (mut wide, mut todo, mut leaves) = (Vec::new(), vec![0usize], Vec::new());
        while let Some(n) = todo.pop() {
            wide.push(n);
            let mut kids = Vec::new();
            plan.open(b2, n, &mut kids);
            assert!((2..=WIDTH).contains(&kids.len()), "a wide node of {} children", kids.len());
            leaves.extend(kids.iter().copied().filter(|&k| b2[k].is_leaf()));
            todo.extend(kids.into_iter().filter(|&k| !b2[k].is_leaf()));
        }
        leaves.sort_unstable();
        let all: Vec<usize> = (0..b2.len()).filter(|&k| b2[k].is_leaf()).collect();
        assert_eq!(leaves, all, "every leaf once");
        wide
    }

    #[test]
    fn the_collapse_finds_the_wide_tree_of_least_area() {
        // Random trees of up to 15 inner nodes, from boxes of mixed sizes (so that the
        // greedy choice, opening the largest child first, is sometimes wrong). Every set of
        // inner nodes that holds the root and gives each of them at most WIDTH children is a
        // wide tree; its cost is the sum of their areas. The plan must find the least.
        let mut s = 7u64;
        let mut beaten_greedy = 0;
        for trial in 0..300 {
            let n = 2 + trial % 15;
            let boxes: Vec<Aabb> = (0..n)
                .map(|_| {
                    let c = Vec3A::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 10.0;
                    let e = Vec3A::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s))
                        * if xorshift(&mut s) < 0.2 { 6.0 } else { 0.5 };
                    Aabb::new(c - e, c + e)
                })
                .collect();
            let mut params = BvhBuildParams::medium_build();
            params.max_prims_per_leaf = 1;
            let b2 = build_bvh2(&boxes, params, &mut Default::default()).nodes;
            let inner: Vec<usize> = (0..b2.len()).filter(|&k| !b2[k].is_leaf()).collect();
            let area = |k: usize| b2[k].aabb().half_area();
            // The children of wide node `w` given which inner nodes are wide.
            let frontier = |w: usize, wide: &dyn Fn(usize) -> bool| {
                let (mut count, mut todo) =
                    (0, vec![b2[w].first_index as usize, b2[w].first_index as usize + 1]);
                while let Some(k) = todo.pop() {
                    if b2[k].is_leaf() || wide(k) {
                        count += 1;
                    } else {
                        todo.extend([b2[k].first_index as usize, b2[k].first_index as usize + 1]);
                    }
                }
                count
            };
            let mut best = f32::INFINITY;
            for set in 0u32..1 << inner.len() {
                let wide = |k: usize| inner.iter().position(|&i| i == k).is_some_and(|i| set >> i & 1 != 0);
                if !wide(0) {
                    continue;
                }
                let members = inner.iter().copied().filter(|&k| wide(k));
                if members.clone().all(|w| frontier(w, &wide) <= WIDTH) {
                    best = best.min(members.map(area).sum());
                }
            }
            let plan = SlotPlan::of(&b2);
            let chosen = opened(&b2, &plan);
            let cost: f32 = chosen.iter().map(|&k| area(k)).sum();
            assert!((cost - best).abs() <= 1e-4 * best, "trial {trial}: {cost} against the least, {best}");
            assert!(
                (plan.cost[0][0] - cost).abs() <= 1e-4 * cost,
                "trial {trial}: planned {} made {cost}",
                plan.cost[0][0]
            );
            // The greedy collapse this replaced, for comparison: open the largest inner child.
            let (mut greedy, mut todo) = (0.0, vec![0usize]);
            while let Some(w) = todo.pop() {
                greedy += area(w);
                let mut kids = vec![b2[w].first_index as usize, b2[w].first_index as usize + 1];
                while kids.len() < WIDTH {
                    let open = (0..kids.len())
                        .filter(|&k| !b2[kids[k]].is_leaf())
                        .max_by(|&a, &b| area(kids[a]).total_cmp(&area(kids[b])));
                    let Some(k) = open else { break };
                    let first = b2[kids[k]].first_index as usize;
                    kids[k] = first;
                    kids.push(first + 1);
                }
                todo.extend(kids.into_iter().filter(|&k| !b2[k].is_leaf()));
            }
            assert!(cost <= greedy * (1.0 + 1e-5), "trial {trial}: {cost} against greedy {greedy}");
            beaten_greedy += usize::from(cost < greedy * (1.0 - 1e-4));
        }
        assert!(beaten_greedy > 0, "no tree where the greedy collapse was worse: the test tests nothing new");

        // Areas that are infinite or NaN (boxes past f32's range) still give a valid wide tree.
        let mut params = BvhBuildParams::medium_build();
        params.max_prims_per_leaf = 1;
        let boxes: Vec<Aabb> = (0..40)
            .map(|i| {
                let c = Vec3A::splat(i as f32);
                let e = if i % 3 == 0 { Vec3A::splat(f32::MAX) } else { Vec3A::splat(0.5) };
                Aabb::new(c - e, c + e)
            })
            .collect();
        let mut b2 = build_bvh2(&boxes, params, &mut Default::default()).nodes;
        for node in b2.iter_mut().step_by(5) {
            node.aabb.max.x = f32::NAN;
        }
        let plan = SlotPlan::of(&b2);
        assert!(opened(&b2, &plan).len() >= 40 / WIDTH);
    }

    /// A soup of random triangles of mixed sizes, a fifth of them perpendicular to an axis.
    fn soup(n: usize, seed: u64) -> Vec<Shape> {
        let mut s = seed;
        let mut m = Mesh::default();
        for i in 0..n {
            let c = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 10.0;
            let size = if i % 7 == 0 { 3.0 } else { 0.3 };
            for _ in 0..3 {
                let mut p =
                    c + (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5) * size;
                if i % 5 == 1 {
                    p[i % 3] = c[i % 3]; // flat along one axis, like a box's wall: a flat box
                }
                m.positions.push(p);
            }
            let b = 3 * i as u32;
            m.tris.push([b, b + 1, b + 2]);
        }
        vec![Shape {
            geometry: Geometry::Mesh(m),
            bsdf: 0,
            light: None,
            flip_normals: false,
            name: "soup".into(),
        }]
    }

    /// The leaves of a tree: (count, all triangles) for each leaf child reference.
    fn leaves(accel: &Accel) -> Vec<(u32, bool)> {
        let mut out = Vec::new();
        for node in &accel.nodes {
            for (lane, &c) in node.child.iter().enumerate() {
                if node.used >> lane & 1 != 0 && c & LEAF != 0 {
                    out.push((((c >> FIRST_BITS) & 3) + 1, c & TRI_LEAF != 0));
                }
            }
        }
        out
    }

    /// A rectangle's two triangles (each one's box is the whole rectangle's) make one leaf,
    /// tested once; two small triangles far apart stay two leaves (their common box is far
    /// larger than theirs).
    #[test]
    fn small_triangle_subtrees_become_one_leaf_where_the_areas_say() {
        let rect = |m: Mesh| Shape {
            geometry: Geometry::Mesh(m),
            bsdf: 0,
            light: None,
            flip_normals: false,
            name: "rect".into(),
        };
        let accel = Accel::build(&[rect(Mesh::rectangle())]);
        assert_eq!(leaves(&accel), [(2, true)]);
        let mut far = Mesh::default();
        for (i, x) in [0.0f32, 100.0].into_iter().enumerate() {
            far.positions.extend([
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(x + 1.0, 0.0, 0.0),
                Vec3::new(x, 1.0, 0.0),
            ]);
            let b = 3 * i as u32;
            far.tris.push([b, b + 1, b + 2]);
        }
        let accel = Accel::build(&[rect(far)]);
        assert_eq!(leaves(&accel), [(1, true), (1, true)]);
    }

    /// Every kernel finds exactly what testing every primitive finds: the same closest hit
    /// (distance and triangle) and the same occlusion answer, for rays from inside and outside
    /// the soup, axis-aligned ones included.
    /// Every kernel finds what brute force finds, in one tree and in trees built in batches
    /// (of 300 and of 7 primitives: a tree over 286 batch trees).
    #[test]
    fn traversal_matches_brute_force_for_every_kernel() {
        for (n, seed, batch) in [(1, 1, BATCH), (5, 2, BATCH), (2000, 3, BATCH), (2000, 4, 300), (2000, 5, 7)]
        {
            let shapes = soup(n, seed);
            let mut accel = Accel::build_in_batches(&shapes, &[], batch);
            assert!(accel.flat_boxes(), "a small tree's planes are decoded");
            let Geometry::Mesh(mesh) = &shapes[0].geometry else { unreachable!() };
            let mut s = seed * 77 + 1;
            for ray_index in 0..3000 {
                let o = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 14.0 - 2.0;
                let mut d = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5;
                if ray_index % 5 == 0 {
                    d = [Vec3::X, Vec3::NEG_Y, Vec3::Z, Vec3::NEG_X][ray_index / 5 % 4];
                }
                let mut ray = Ray::new(o, d.normalize());
                if ray_index % 3 == 0 {
                    ray.tmax = 4.0;
                }
                let pre = RayPre::new(ray.d);
                let mut brute: Option<(f32, usize)> = None;
                for i in 0..mesh.tris.len() {
                    let [a, b, c] = mesh.tri(i);
                    if let Some((t, ..)) = intersect_triangle(&ray, &pre, ray.tmax, a, b, c) {
                        if t < ray.tmax && brute.is_none_or(|(bt, _)| t < bt) {
                            brute = Some((t, i));
                        }
                    }
                }
                for (kernel, flat) in Kernel::available().into_iter().flat_map(|k| [(k, true), (k, false)]) {
                    accel.set_kernel(kernel);
                    accel.set_flat(flat);
                    let hit = accel.intersect(&shapes, &ray).map(|it| (it.t, it.prim as usize));
                    assert_eq!(
                        hit.map(|h| h.0),
                        brute.map(|b| b.0),
                        "{kernel:?}, flat {flat}, n {n}, batch {batch}, ray {ray_index}"
                    );
                    assert_eq!(
                        accel.occluded(&shapes, &ray),
                        brute.is_some(),
                        "{kernel:?}, flat {flat}, ray {ray_index}"
                    );
                }
            }
        }
    }

    /// An 8 x 8 grid of unit squares at z = 0 (every third square's first triangle doubled),
    /// a soup of 600 triangles (seed `soup_seed`) and 150 small balls among them (seed
    /// `ball_seed`): leaves that mix balls and triangles.
    fn grid_soup_and_balls(soup_seed: u64, ball_seed: u64) -> Vec<Shape> {
        let n = 8u32;
        let mut grid = Mesh::default();
        for y in 0..=n {
            for x in 0..=n {
                grid.positions.push(Vec3::new(x as f32, y as f32, 0.0));
            }
        }
        for y in 0..n {
            for x in 0..n {
                let i = y * (n + 1) + x;
                grid.tris.push([i, i + 1, i + n + 2]);
                grid.tris.push([i, i + n + 2, i + n + 1]);
                if (x + y) % 3 == 0 {
                    grid.tris.push([i, i + 1, i + n + 2]); // a coincident copy
                }
            }
        }
        let mut shapes = soup(600, soup_seed);
        shapes.push(shape(Geometry::Mesh(grid), "grid"));
        let mut s = ball_seed;
        for k in 0..150 {
            let center = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 10.0;
            let ball =
                crate::geometry::Sphere { center, radius: 0.15, rot: glam::Mat3::IDENTITY, tangents: true };
            shapes.push(shape(Geometry::Sphere(ball), &format!("ball {k}")));
        }
        shapes
    }

    /// Rays down and up onto [`grid_soup_and_balls`]'s grid every quarter unit (its vertices
    /// and edges among them) and slanted ones, then 4,000 random rays (seed `seed`), a third
    /// of them ending among the triangles.
    fn grid_rays(seed: u64) -> Vec<Ray> {
        let n = 8;
        let mut rays = Vec::new();
        for k in 0..=4 * n {
            for j in 0..=4 * n {
                let (x, y) = (k as f32 * 0.25, j as f32 * 0.25);
                rays.push(Ray::new(Vec3::new(x, y, 3.0), Vec3::NEG_Z));
                rays.push(Ray::new(Vec3::new(x, y, -3.0), Vec3::Z));
                rays.push(Ray::new(Vec3::new(x + 0.3, y - 0.2, 2.0), Vec3::new(-0.3, 0.2, -2.0).normalize()));
            }
        }
        let mut s = seed;
        for k in 0..4000 {
            let o = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 14.0 - 2.0;
            let d = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5;
            let mut ray = Ray::new(o, d.normalize());
            if k % 3 == 0 {
                ray.tmax = 4.0 + xorshift(&mut s) * 4.0; // ends among the triangles
            }
            rays.push(ray);
        }
        rays
    }

    /// Leaves of triangles tested together (the x86 kernels' quads) find bit for bit what
    /// testing them one at a time (the scalar kernel) finds: distance, triangle, barycentrics
    /// and point, and the same occlusion answer. Rays straight down onto a grid's vertices and
    /// edges (edge functions exactly 0: the quad hands the leaf to the one-at-a-time test),
    /// coincident triangles (ties: the first in leaf order wins), rays from the surface itself
    /// and random rays, some ending short, through a soup with balls among its triangles. The
    /// leaves of two or more balls alone, which the x86 kernels test together too
    /// (`x86::balls_sse`), likewise.
    #[test]
    fn triangle_quads_match_one_at_a_time() {
        let shapes = grid_soup_and_balls(21, 17);
        let accel_of = |kernel| {
            let mut a = Accel::build(&shapes);
            a.set_kernel(kernel);
            a
        };
        let kernels = Kernel::available();
        let accels: Vec<Accel> = kernels.iter().map(|&k| accel_of(k)).collect();
        assert_eq!(kernels.last(), Some(&Kernel::Scalar), "the reference is last");
        assert!(accels[0].nodes.len() > 1 && accels[0].tris.index.len() > 100);
        let a = &accels[0];
        let ball_leaves = a
            .nodes
            .iter()
            .flat_map(|n| (0..WIDTH).filter(|&i| n.used >> i & 1 != 0).map(|i| n.child[i]))
            .filter(|&c| c & LEAF != 0)
            .filter(|&c| {
                let count = ((c & COUNT) >> FIRST_BITS) + 1;
                count > 1 && a.leaf_balls(&shapes, c & FIRST, count).is_some()
            })
            .count();
        assert!(ball_leaves >= 5, "{ball_leaves} leaves of balls alone");
        let rays = grid_rays(5);
        let (mut hits, mut on_edges) = (0, 0);
        for (r, ray) in rays.iter().enumerate() {
            let key = |a: &Accel| {
                a.intersect(&shapes, ray).map(|it| {
                    (
                        it.t.to_bits(),
                        it.shape,
                        it.prim,
                        it.uv.to_array().map(f32::to_bits),
                        it.p.to_array().map(f32::to_bits),
                    )
                })
            };
            let scalar = key(&accels[accels.len() - 1]);
            for (a, kernel) in accels.iter().zip(&kernels) {
                assert_eq!(key(a), scalar, "{kernel:?}, ray {r}: {ray:?}");
                assert_eq!(a.occluded(&shapes, ray), scalar.is_some(), "{kernel:?}, ray {r}");
                // Again from the hit point, along the surface's other side.
                if let Some(it) = a.intersect(&shapes, ray) {
                    let next = it.spawn_ray(ray.d);
                    let again = |b: &Accel| b.intersect(&shapes, &next).map(|h| (h.t.to_bits(), h.prim));
                    assert_eq!(again(a), again(&accels[accels.len() - 1]), "{kernel:?}, ray {r} spawned");
                }
            }
            hits += scalar.is_some() as u32;
            // Straight down onto a grid line or a square's diagonal: an edge function is 0.
            let (fx, fy) = (ray.o.x.fract(), ray.o.y.fract());
            on_edges +=
                (ray.d == Vec3::NEG_Z && scalar.is_some() && (fx == 0.0 || fy == 0.0 || fx == fy)) as u32;
        }
        assert!(hits > 3000 && on_edges > 100, "hits {hits}, rays onto edges {on_edges}");
    }

    /// Leaves of balls alone, tested together on the x86 kernels (`x86::balls_sse`), find what
    /// the scalar kernel finds one ball at a time, bit for bit: the distance, the ball (ties
    /// between coincident balls go to the first in leaf order) and the leaf, and the same
    /// occlusion answer. Clusters of four balls (two coincident, two overlapping them), rays
    /// from outside and from inside the balls, some ending short.
    #[test]
    fn ball_leaves_match_one_at_a_time() {
        let ball = |center: Vec3, radius: f32| {
            let b = super::super::Sphere { center, radius, rot: glam::Mat3::IDENTITY, tangents: true };
            shape(Geometry::Sphere(b), "ball")
        };
        let mut shapes = Vec::new();
        let mut centres = Vec::new();
        for c in 0..12 {
            let o = Vec3::new((c % 4) as f32 * 3.0, (c / 4) as f32 * 3.0, 0.0);
            shapes.extend([
                ball(o, 0.5),
                ball(o, 0.5),
                ball(o + Vec3::new(0.3, 0.0, 0.0), 0.4),
                ball(o + Vec3::new(0.0, 0.2, 0.1), 0.25),
            ]);
            centres.push(o);
        }
        let mut accel = Accel::build(&shapes);
        let ball_leaf = |a: &Accel, c: u32| {
            let count = ((c & COUNT) >> FIRST_BITS) + 1;
            c & LEAF != 0
                && c & TRI_LEAF == 0
                && count > 1
                && a.leaf_balls(&shapes, c & FIRST, count).is_some()
        };
        let kernels = Kernel::available();
        assert_eq!(kernels.last(), Some(&Kernel::Scalar), "the reference is last");
        let mut s = 77;
        let (mut in_ball_leaves, mut from_inside) = (0, 0);
        for r in 0..6000 {
            let target =
                centres[r % 12] + (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5);
            let o = if r % 4 == 0 {
                from_inside += 1;
                centres[r % 12]
                    + (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5) * 0.3
            } else {
                target
                    + (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5)
                        .normalize_or(Vec3::Z)
                        * 6.0
            };
            let mut ray = Ray::new(o, (target - o).normalize_or(Vec3::X));
            if r % 3 == 0 {
                ray.tmax = (target - o).length();
            }
            let mut keys = Vec::new();
            for &kernel in &kernels {
                accel.set_kernel(kernel);
                let hit = accel.closest(&shapes, &ray, SpawnedFrom::NOTHING);
                let key = hit.map(|h| (h.t.to_bits(), h.k, h.leaf));
                assert_eq!(accel.occluded(&shapes, &ray), key.is_some(), "{kernel:?}, ray {r}");
                keys.push((kernel, key));
            }
            let (_, want) = keys[keys.len() - 1];
            for (kernel, key) in &keys {
                assert_eq!(*key, want, "{kernel:?}, ray {r}: {ray:?}");
            }
            in_ball_leaves += want.is_some_and(|(_, _, leaf)| ball_leaf(&accel, leaf)) as u32;
        }
        assert!(in_ball_leaves > 2000 && from_inside > 1000, "{in_ball_leaves} hits in leaves of balls");
    }

    /// Packets of eight rays (`intersect_among_packet`) find what each ray's own query finds,
    /// bit for bit, on every kernel: leaves of triangles (some coincident, rays straight onto
    /// their edges, where a lane takes the scalar test) and of spheres, packets whose rays share
    /// the triangle test's axes and packets whose rays do not, rays that end among the
    /// triangles, and packets of one to eight rays.
    #[test]
    fn packets_find_what_each_ray_finds() {
        let shapes = grid_soup_and_balls(23, 19);
        let rays = grid_rays(7);
        // In the given order most packets mix the axes; sorted by them, most share them.
        let axes = |r: &Ray| {
            let p = RayPre::new(r.d);
            (p.kx, p.ky, p.kz)
        };
        let mut sorted = rays.clone();
        sorted.sort_by_key(axes);
        let key = |h: Option<Hit>| h.map(|h| (h.t.to_bits(), h.k, h.aux.to_array().map(f32::to_bits)));
        for kernel in Kernel::available() {
            let mut accel = Accel::build(&shapes);
            accel.set_kernel(kernel);
            // Every leaf, each at distance 0: a lower bound for every ray, so each ray's query
            // tests them all.
            let mut cands = Candidates { leaves: Vec::new(), complete: true };
            for node in &accel.nodes {
                for (lane, &c) in node.child.iter().enumerate() {
                    if node.used >> lane & 1 != 0 && c & LEAF != 0 {
                        cands.leaves.push((0.0, c));
                    }
                }
            }
            assert!(cands.leaves.len() > 100);
            let (mut shared, mut hits, mut size) = (0, 0, 0);
            for order in [&rays, &sorted] {
                let mut at = 0;
                while at < order.len() {
                    size = size % PACKET + 1; // 1, 2, ..., 8, 1, ...
                    let packet = &order[at..(at + size).min(order.len())];
                    at += packet.len();
                    let mut out = [None; PACKET];
                    accel.intersect_among_packet(&shapes, packet, &cands, &mut out[..packet.len()]);
                    shared += packet.iter().all(|r| axes(r) == axes(&packet[0])) as u32;
                    for (j, ray) in packet.iter().enumerate() {
                        let own = accel.among_hit(&shapes, ray, &cands);
                        assert_eq!(
                            key(out[j]),
                            key(own),
                            "{kernel:?}: lane {j} of {}: {ray:?}",
                            packet.len()
                        );
                        // The same hit as the whole tree's query, up to which of two coincident
                        // triangles.
                        let whole = accel.intersect(&shapes, ray).map(|it| it.t.to_bits());
                        assert_eq!(out[j].map(|h| h.t.to_bits()), whole, "{kernel:?}: {ray:?}");
                        if let Some(h) = out[j] {
                            let it = accel.hit_interaction(&shapes, ray, &h);
                            assert_eq!(it.t.to_bits(), h.t.to_bits());
                            hits += 1;
                        }
                    }
                }
            }
            assert!(
                shared > 400 && hits > 4000,
                "{kernel:?}: {shared} packets share their axes, {hits} hits"
            );
        }
    }

    fn shape(geometry: Geometry, name: &str) -> Shape {
        Shape { geometry, bsdf: 0, light: None, flip_normals: false, name: name.into() }
    }

    /// Triangles in one plane, up to their vertices' rounding: a transformed rectangle's are;
    /// a quad folded by 1e-4 radians, or a degenerate first triangle, are not.
    #[test]
    fn coplanar_takes_rounding_not_folds() {
        let placed = glam::Mat4::from_scale_rotation_translation(
            Vec3::new(50.0, 0.37, 3.0),
            glam::Quat::from_euler(glam::EulerRot::XYZ, -1.5707964, 0.3, 0.1),
            Vec3::new(-7.0, 1e3, 0.25),
        );
        let tris = |m: &Mesh| -> Vec<[Vec3; 3]> { (0..m.tris.len()).map(|i| m.tri(i)).collect() };
        assert!(coplanar(tris(&Mesh::placed_rectangle(&placed)).iter()));
        let mut folded = Mesh::rectangle();
        folded.positions[2].z = 2e-4; // the far corner of the second triangle lifted
        assert!(!coplanar(tris(&folded).iter()));
        folded.transform_flat(&placed);
        assert!(!coplanar(tris(&folded).iter()));
        let flat = [Vec3::ZERO, Vec3::X, Vec3::X * 2.0];
        assert!(!coplanar([flat, [Vec3::ZERO, Vec3::X, Vec3::Y]].iter()), "a degenerate first triangle");
        assert!(!coplanar([[Vec3::ZERO, Vec3::X, Vec3::Y], flat].iter()), "a degenerate later triangle");
        // A 3-degree fold of a small leaf far from the origin, within 4 ulps of its largest
        // coordinate (what the first tolerance let through; review of c7a24bf).
        let a = [Vec3::new(1000.0, 0.5, 0.0), Vec3::new(1000.01, 0.5, 0.0), Vec3::new(1000.0, 0.5, 0.01)];
        let b =
            [Vec3::new(1000.01, 0.5, 0.0), Vec3::new(1000.01, 0.5004, 0.01), Vec3::new(1000.0, 0.5, 0.01)];
        assert!(!coplanar([a, b].iter()));
        // Two parallel planes 1e-4 apart (a decal, a light under a ceiling).
        let lifted = [Vec3::new(0.0, 0.0, 1e-4), Vec3::new(1.0, 0.0, 1e-4), Vec3::new(0.0, 1.0, 1e-4)];
        assert!(!coplanar([[Vec3::ZERO, Vec3::X, Vec3::Y], lifted].iter()));
        // A quad 1e4 from the origin whose fourth corner lies on the plane of the other three
        // up to its rounding (5e-4 at that distance): 1.5e-4 off, not flat. (A
        // transformed rectangle's corners there round to a parallelogram, which is.)
        let [p0, p1, p2] = [
            Vec3::new(1e4 + 0.1, 1e4 + 0.2, 1e4 + 0.3),
            Vec3::new(1e4 + 1.7, 1e4 - 0.4, 1e4 + 0.9),
            Vec3::new(1e4 - 0.3, 1e4 + 1.1, 1e4 + 1.4),
        ]
        .map(|v| v.as_dvec3());
        let p3 = (p0 + (p1 - p0) * 0.37 + (p2 - p0) * 1.3).as_vec3();
        let (dev, size) = {
            let n = (p1 - p0).cross(p2 - p0).normalize();
            (n.dot(p3.as_dvec3() - p0).abs(), (p2 - p1).length())
        };
        assert!(dev > 10.0 * FLAT * size, "the fourth corner {dev} off the plane");
        let [p0, p1, p2] = [p0, p1, p2].map(|v| v.as_vec3());
        assert!(!coplanar([[p0, p1, p2], [p0, p2, p3]].iter()));
    }

    /// The review's case against the first tolerance: a small leaf 1000 from the origin,
    /// folded by 3 degrees; a ray leaving one triangle nearly along it meets the other, with
    /// and without the skip.
    #[test]
    fn a_small_fold_far_away_keeps_its_hit() {
        let mut m = Mesh::default();
        m.positions = vec![
            Vec3::new(1000.0, 0.5, 0.0),
            Vec3::new(1000.01, 0.5, 0.0),
            Vec3::new(1000.0, 0.5, 0.01),
            Vec3::new(1000.01, 0.5004, 0.01),
        ];
        m.tris = vec![[0, 1, 2], [1, 3, 2]];
        let shapes = vec![shape(Geometry::Mesh(m), "fold")];
        let accel = Accel::build(&shapes);
        let down = Ray::new(Vec3::new(1000.003, 1.5, 0.003), Vec3::NEG_Y);
        let hit = accel.closest(&shapes, &down, SpawnedFrom::NOTHING).expect("the first triangle");
        let it = accel.hit_interaction(&shapes, &down, &hit);
        assert_eq!(it.prim, 0);
        let d = Vec3::new(1.0, 0.01, 1.0).normalize();
        let ray = it.spawn_ray(d);
        let from = accel.spawned_from(&shapes, &hit, &it, d);
        assert_eq!(from.leaf, 0, "the fold taken as a plane");
        let fast = accel.closest(&shapes, &ray, from).map(|h| accel.hit_interaction(&shapes, &ray, &h).prim);
        assert_eq!(fast, Some(1));
    }

    /// A tree that is one leaf (a rectangle, a ball, a disk alone) knows it (`Accel::lone`), and
    /// the queries of rays that leave it end at once: with the answer of the query that tests
    /// it (nothing), for closest and any hits. A ray into the ball keeps its hit; a tree of two
    /// leaves has no lone leaf.
    #[test]
    fn rays_leaving_a_lone_leaf_meet_nothing() {
        let wall = glam::Mat4::from_scale_rotation_translation(
            Vec3::new(2.0, 0.7, 1.0),
            glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, 0.5, 0.2),
            Vec3::ZERO,
        );
        let ball = Geometry::Sphere(super::super::Sphere {
            center: Vec3::ZERO,
            radius: 0.8,
            rot: glam::Mat3::IDENTITY,
            tangents: true,
        });
        let disk = Geometry::Disk(super::super::Disk::new(glam::Mat4::from_rotation_x(1.2)));
        let mut s = 99;
        for (name, geometry) in
            [("wall", Geometry::Mesh(Mesh::placed_rectangle(&wall))), ("ball", ball), ("disk", disk)]
        {
            let shapes = vec![shape(geometry, name)];
            let accel = Accel::build(&shapes);
            assert_ne!(accel.lone, 0, "{name}: one leaf");
            let (mut left, mut into) = (0, 0);
            for _ in 0..3000 {
                let target = (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5) * 0.8;
                let dir = (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5)
                    .normalize_or(Vec3::Z);
                let ray = Ray::new(target + dir * 9.0, -dir);
                let Some(hit) = accel.closest(&shapes, &ray, SpawnedFrom::NOTHING) else { continue };
                let it = accel.hit_interaction(&shapes, &ray, &hit);
                let d = crate::math::square_to_uniform_sphere(glam::Vec2::new(
                    xorshift(&mut s),
                    xorshift(&mut s),
                ));
                let ray = it.spawn_ray(d);
                let from = accel.spawned_from(&shapes, &hit, &it, d);
                let full = accel.closest(&shapes, &ray, SpawnedFrom::piece(it.leaving())).map(|h| h.t);
                let fast = accel.closest(&shapes, &ray, from).map(|h| h.t);
                assert_eq!(full, fast, "{name}: along {d}");
                assert_eq!(accel.occluded_from(&shapes, &ray, from), full.is_some(), "{name}");
                if from.leaf == accel.lone {
                    assert_eq!(fast, None, "{name}: a ray leaving the lone leaf");
                    left += 1;
                } else {
                    into += 1;
                }
            }
            assert!(left > 1000, "{name}: {left} rays left the leaf");
            assert_eq!(into > 0, name == "ball", "{name}: {into} rays went back in");
        }
        let two = vec![
            shape(Geometry::Mesh(Mesh::placed_rectangle(&wall)), "wall"),
            shape(
                Geometry::Mesh(Mesh::placed_rectangle(&glam::Mat4::from_translation(Vec3::Z * 5.0))),
                "far",
            ),
        ];
        assert_eq!(Accel::build(&two).lone, 0, "two leaves");
    }

    /// Rays spawned as the integrator spawns them, from hits on a placed rectangle, a folded
    /// quad, spheres (one with flipped normals), a disk and a cube, get from
    /// `Accel::spawned_from`'s skip exactly the closest hit that the query without it gets,
    /// and `occluded_from` agrees. The skip is taken on the rectangle, the disk and rays
    /// leaving a sphere, never by rays into a sphere (they hit it again) nor on the folded
    /// quad, whose triangles share a leaf: rays from one of them to the other keep that hit.
    #[test]
    fn rays_skip_only_leaves_they_cannot_meet_again() {
        let sphere = |c: Vec3, r: f32, flip: bool| Shape {
            flip_normals: flip,
            ..shape(
                Geometry::Sphere(super::super::Sphere {
                    center: c,
                    radius: r,
                    rot: glam::Mat3::IDENTITY,
                    tangents: true,
                }),
                "ball",
            )
        };
        let wall = glam::Mat4::from_scale_rotation_translation(
            Vec3::new(2.0, 0.7, 1.0),
            glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, 0.5, 0.2),
            Vec3::new(0.0, 0.0, -3.0),
        );
        let mut folded = Mesh::rectangle();
        folded.positions[2].z = 0.3; // the second triangle ([0, 2, 3]) tilts up towards +z
        folded.transform_flat(&glam::Mat4::from_translation(Vec3::new(3.0, 0.0, 0.0)));
        let mut cube = Mesh::cube();
        cube.transform_flat(&glam::Mat4::from_scale_rotation_translation(
            Vec3::splat(0.6),
            glam::Quat::from_rotation_y(0.4),
            Vec3::new(-3.0, 0.5, 0.0),
        ));
        let disk = glam::Mat4::from_rotation_translation(
            glam::Quat::from_rotation_x(1.2),
            Vec3::new(0.0, -2.5, 0.5),
        );
        let shapes = vec![
            shape(Geometry::Mesh(Mesh::placed_rectangle(&wall)), "wall"),
            shape(Geometry::Mesh(folded), "folded"),
            sphere(Vec3::new(0.0, 2.5, 0.0), 0.8, false),
            sphere(Vec3::new(2.5, 2.5, 0.5), 0.5, true),
            shape(Geometry::Disk(super::super::Disk::new(disk)), "disk"),
            shape(Geometry::Mesh(cube), "cube"),
        ];
        let accel = Accel::build(&shapes);
        let centres = [
            Vec3::new(0.0, 0.0, -3.0),
            Vec3::new(3.5, 0.5, 0.0),
            Vec3::new(0.0, 2.5, 0.0),
            Vec3::new(2.5, 2.5, 0.5),
            Vec3::new(0.0, -2.5, 0.5),
            Vec3::new(-3.0, 0.5, 0.0),
        ];
        let mut s = 4242;
        let mut skipped = [0u32; 6]; // rays that skipped their leaf, by the shape they left
        let (mut spawned, mut into_balls, mut folded_leaf) = (0, 0, None);
        for round in 0..30_000 {
            let target = centres[round % 6]
                + (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5) * 2.0;
            let o = target
                + (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5)
                    .normalize_or(Vec3::Z)
                    * 9.0;
            let ray = Ray::new(o, (target - o).normalize());
            let Some(hit) = accel.closest(&shapes, &ray, SpawnedFrom::NOTHING) else { continue };
            let it = accel.hit_interaction(&shapes, &ray, &hit);
            if it.shape == 1 {
                // Both triangles of the folded quad in one leaf, never taken as a plane.
                assert_eq!(*folded_leaf.get_or_insert(hit.leaf), hit.leaf, "the folded quad in two leaves");
            }
            let mut dirs: Vec<Vec3> = (0..4)
                .map(|_| {
                    crate::math::square_to_uniform_sphere(glam::Vec2::new(xorshift(&mut s), xorshift(&mut s)))
                })
                .collect();
            if it.shape == 1 && it.prim == 0 {
                // Towards a point of the tilted triangle, on its side: a hit on the same leaf.
                let (b1, b2) = (xorshift(&mut s), xorshift(&mut s));
                let (b1, b2) = if b1 + b2 > 1.0 { (1.0 - b1, 1.0 - b2) } else { (b1, b2) };
                let [p0, p2, p3] = [0, 2, 3].map(|v| match &shapes[1].geometry {
                    Geometry::Mesh(m) => m.positions[v],
                    _ => unreachable!(),
                });
                dirs.push((p0 + (p2 - p0) * b1 + (p3 - p0) * b2 - it.p).normalize());
            }
            for (k, d) in dirs.into_iter().enumerate() {
                let ray = it.spawn_ray(d);
                let from = accel.spawned_from(&shapes, &hit, &it, d);
                let full = accel.closest(&shapes, &ray, SpawnedFrom::piece(it.leaving()));
                let fast = accel.closest(&shapes, &ray, from);
                let key = |h: Option<Hit>| {
                    h.map(|h| {
                        let i = accel.hit_interaction(&shapes, &ray, &h);
                        (h.t, i.shape, i.prim)
                    })
                };
                assert_eq!(
                    key(full),
                    key(fast),
                    "round {round}: from shape {} prim {} along {d}",
                    it.shape,
                    it.prim
                );
                assert_eq!(accel.occluded_from(&shapes, &ray, from), fast.is_some());
                spawned += 1;
                if from.leaf != 0 {
                    assert_eq!(from.leaf, hit.leaf);
                    skipped[it.shape as usize] += 1;
                }
                let inward = it.ng.dot(d) < 0.0;
                match it.shape {
                    2 | 3 if (it.shape == 3) != inward => {
                        // Into the ball: no skip, and the ball is met again from inside.
                        assert_eq!(from.leaf, 0);
                        assert_eq!(key(fast).map(|h| h.1), Some(it.shape), "a ray into a ball left it");
                        into_balls += 1;
                    }
                    2 | 3 | 0 | 4 => assert_ne!(from.leaf, 0, "shape {} not skipped", it.shape),
                    1 => {
                        assert_eq!(from.leaf, 0, "the folded quad taken as a plane");
                        if k == 4 {
                            assert_eq!(
                                key(fast).map(|h| (h.1, h.2)),
                                Some((1, 1)),
                                "the fold's other side lost"
                            );
                        }
                    }
                    _ => {}
                }
            }
        }
        assert!(folded_leaf.is_some());
        // (The cube's faces are leaves of two triangles each: they are skipped too.)
        assert!(
            skipped[0] > 2000
                && skipped[2] > 1000
                && skipped[3] > 500
                && skipped[4] > 1000
                && skipped[5] > 1000,
            "{skipped:?}"
        );
        assert!(into_balls > 1000 && spawned > 50_000, "{into_balls} into balls, {spawned} rays");
    }

    /// Through the tree: rays spawned from fibre hits (`Accel::intersect`, then
    /// `Interaction::spawn_ray` and `Interaction::leaving`) never get a hit on the piece they
    /// leave from `Accel::closest`, and otherwise get what the full query gets;
    /// `Accel::occluded_from` agrees with it. The fibres are the second shape, after a
    /// mesh, so that the skip must match the shape index without the primitive's flags. A
    /// group of other fibres is placed twice, the second copy 3e-3 from the first (within a
    /// fibre's radius), so that a ray leaving a piece of one copy often meets the same piece
    /// of the other: that hit is another surface and must stay.
    #[test]
    fn rays_leaving_fibres_through_the_tree_skip_only_their_piece() {
        use crate::geometry::curves::Curves;
        use crate::geometry::Instance;
        let mut s = 77;
        let fibres = |s: &mut u64| {
            let curves: Vec<Vec<(Vec3, f32)>> = (0..40)
                .map(|_| {
                    let root = Vec3::new(xorshift(s), xorshift(s), xorshift(s)) * 0.2;
                    let dir = (Vec3::new(xorshift(s), xorshift(s), xorshift(s)) - 0.5).normalize_or(Vec3::Y);
                    (0..6)
                        .map(|k| {
                            let bend = (Vec3::new(xorshift(s), xorshift(s), xorshift(s)) - 0.5) * 0.01;
                            (root + dir * (0.02 * k as f32) + bend, 0.004 - 0.0005 * k as f32)
                        })
                        .collect()
                })
                .collect();
            Curves::linear(&curves)
        };
        let group_fibres = fibres(&mut s);
        let bounds = (0..group_fibres.segments.len())
            .map(|k| group_fibres.bounds(k))
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), (a, b)| (lo.min(a), hi.max(b)));
        let placed = glam::Mat4::from_translation(Vec3::new(0.0, 0.0, 5.0))
            * glam::Mat4::from_quat(glam::Quat::from_rotation_y(0.7))
            * glam::Mat4::from_scale(Vec3::new(1.0, 1.7, 0.6));
        let beside = glam::Mat4::from_translation(Vec3::new(0.003, 0.0, 0.0)) * placed;
        let shapes = vec![
            soup(50, 9).remove(0),
            shape(Geometry::Curves(fibres(&mut s)), "fur"),
            shape(Geometry::Curves(group_fibres), "grouped fur"),
            shape(Geometry::Instance(Instance::new(0, placed, Some(bounds))), "instance"),
            shape(Geometry::Instance(Instance::new(0, beside, Some(bounds))), "instance beside it"),
        ];
        let accel = Accel::build_grouped(&shapes, &[vec![2]]);
        let (mut from_fibres, mut self_hits, mut other_copy, mut instanced_self_hits) = (0, 0, 0, 0);
        let mut instanced = [0u32; 2]; // hits in each placement
        for round in 0..20_000 {
            let target = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 0.2;
            let target = if round % 4 == 0 { placed.transform_point3(target) } else { target };
            let away = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5;
            let o = target + away.normalize_or(Vec3::Z) * 3.0;
            let d = (target - o).normalize();
            let Some(it) = accel.intersect(&shapes, &Ray::new(o, d)) else { continue };
            let Some(leaving) = it.leaving() else { continue };
            if it.shape == 2 {
                match leaving.instance {
                    Some(k @ (3 | 4)) => instanced[k as usize - 3] += 1,
                    other => panic!("instanced hit in {other:?}"),
                }
            } else {
                assert_eq!((leaving.shape, leaving.segment, leaving.instance), (1, it.prim, None));
            }
            // Four rays spawned as the integrator does, and one from 1e-5 outside the surface
            // heading into the fibre, as a ray would whose offset rounding put on the wrong
            // side (self-hits through rounding alone are rare in instances, whose offsets
            // also bound the transform's rounding).
            let outward = if it.ng.dot(d) < 0.0 { it.ng } else { -it.ng };
            for k in 0..5 {
                let w = crate::math::square_to_uniform_sphere(glam::Vec2::new(
                    xorshift(&mut s),
                    xorshift(&mut s),
                ));
                let ray = match k {
                    4 => Ray::new(it.p + outward * 1e-5, (w * 0.3 - outward).normalize()),
                    _ => it.spawn_ray(w),
                };
                from_fibres += 1;
                let full = accel.intersect(&shapes, &ray);
                let skipped = accel
                    .closest(&shapes, &ray, SpawnedFrom::piece(Some(leaving)))
                    .map(|h| accel.hit_interaction(&shapes, &ray, &h));
                assert_eq!(
                    accel.occluded_from(&shapes, &ray, SpawnedFrom::piece(Some(leaving))),
                    skipped.is_some()
                );
                let on_left = |h: &Interaction| h.leaving() == Some(leaving);
                assert!(!skipped.as_ref().is_some_and(on_left), "the skip returned the piece left");
                let same_piece_elsewhere = |h: &Interaction| {
                    h.leaving().is_some_and(|l| Leaving { instance: leaving.instance, ..l } == leaving)
                };
                if skipped.as_ref().is_some_and(same_piece_elsewhere) {
                    other_copy += 1;
                }
                match &full {
                    Some(h) if on_left(h) => {
                        assert!(h.t < 1e-4, "a hit on the piece left at t {}", h.t);
                        self_hits += 1;
                        instanced_self_hits += leaving.instance.is_some() as u32;
                    }
                    _ => assert_eq!(
                        full.map(|h| (h.t, h.shape, h.prim, h.instance)),
                        skipped.map(|h| (h.t, h.shape, h.prim, h.instance))
                    ),
                }
            }
        }
        eprintln!(
            "{from_fibres} rays from fibres ({instanced:?} hits in the two instances), {self_hits} would hit \
             the piece they leave ({instanced_self_hits} in an instance), {other_copy} hit that \
             piece in the other instance"
        );
        assert!(
            from_fibres > 10_000 && instanced.iter().all(|&n| n > 200) && other_copy > 50,
            "{from_fibres} rays from fibres, {instanced:?} instanced hits, {other_copy} on the other copy"
        );
        assert!(
            self_hits > 100 && instanced_self_hits > 10,
            "{self_hits} self-hits, {instanced_self_hits} in instances"
        );
    }

    /// A tree mostly of fibres builds over pieces of up to `PIECE` joined segments of one
    /// fibre, whole and in batches: every fibre leaf holds exactly one piece (each fibre cut
    /// from its root into pieces of 3 and what is left), and every kernel finds what testing
    /// every segment and triangle finds. The fibres have 1 to 8 segments, so pieces end where
    /// fibres do. With 20 triangles beside the 540 segments, and with exactly as many triangles
    /// as segments (still a tree of pieces), where triangle subtrees must still join into
    /// leaves of up to four.
    #[test]
    fn fibre_pieces_stay_whole_in_leaves_and_find_what_brute_force_finds() {
        use crate::geometry::curves::Curves;
        let mut s = 5;
        let curves: Vec<Vec<(Vec3, f32)>> = (0..120)
            .map(|i| {
                let root = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s));
                let dir = (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5)
                    .normalize_or(Vec3::Y);
                (0..2 + i % 8).map(|k| (root + dir * (0.05 * k as f32), 0.01)).collect()
            })
            .collect();
        let mut pieces = Vec::new(); // (first segment, segments) of every piece
        let mut first = 0;
        for c in &curves {
            let n = c.len() as u32 - 1;
            pieces.extend((0..n).step_by(PIECE as usize).map(|k| (first + k, PIECE.min(n - k))));
            first += n;
        }
        let fur = Curves::linear(&curves);
        let segments = fur.segments.len();
        assert_eq!(first as usize, segments);
        for (triangles, batches) in [(20, vec![BATCH, 40, 7]), (segments, vec![BATCH, 60])] {
            let shapes = vec![soup(triangles, 3).remove(0), shape(Geometry::Curves(fur.clone()), "fur")];
            let Geometry::Mesh(mesh) = &shapes[0].geometry else { unreachable!() };
            let Geometry::Curves(fur) = &shapes[1].geometry else { unreachable!() };
            for batch in batches {
                let what = format!("{triangles} triangles, batch {batch}");
                let mut accel = Accel::build_in_batches(&shapes, &[], batch);
                let (mut leaves, mut joined_triangles) = (Vec::new(), 0);
                for node in &accel.nodes {
                    for (lane, &c) in node.child.iter().enumerate() {
                        if node.used >> lane & 1 == 0 || c & LEAF == 0 {
                            continue;
                        }
                        let (first, count) = ((c & FIRST) as usize, ((c >> FIRST_BITS) & 3) + 1);
                        let prims = &accel.prims[first..first + count as usize];
                        if prims.iter().all(|p| p.shape & CURVE == 0) {
                            joined_triangles += (count > 1) as u32;
                            continue;
                        }
                        for (j, p) in prims.iter().enumerate() {
                            assert_eq!(
                                p.shape & !PLANAR,
                                1 | CURVE,
                                "{what}: a fibre leaf holds only fibres"
                            );
                            assert_eq!(p.index, prims[0].index + j as u32, "{what}: consecutive");
                        }
                        leaves.push((prims[0].index, count));
                    }
                }
                leaves.sort_unstable();
                assert_eq!(leaves, pieces, "{what}: a leaf a piece");
                if triangles == segments {
                    assert!(
                        joined_triangles > triangles as u32 / 8,
                        "{what}: {joined_triangles} joined leaves"
                    );
                }
                let mut fibre_hits = 0;
                for ray_index in 0..1000 {
                    let o = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 3.0 - 1.0;
                    let target = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s));
                    let mut ray = Ray::new(o, (target - o).normalize_or(Vec3::X));
                    if ray_index % 3 == 0 {
                        ray.tmax = 1.5;
                    }
                    let pre = RayPre::new(ray.d);
                    let mut brute = f32::INFINITY;
                    for i in 0..mesh.tris.len() {
                        let [a, b, c] = mesh.tri(i);
                        if let Some((t, ..)) = intersect_triangle(&ray, &pre, ray.tmax, a, b, c) {
                            brute = brute.min(t);
                        }
                    }
                    let mut on_fibre = false;
                    for i in 0..segments {
                        if let Some(h) = fur.intersect(i, ray.o, ray.d, ray.tmin, ray.tmax.min(brute)) {
                            (brute, on_fibre) = (brute.min(h.t), true);
                        }
                    }
                    fibre_hits += on_fibre as u32;
                    let brute = (brute < ray.tmax).then_some(brute);
                    for kernel in Kernel::available() {
                        accel.set_kernel(kernel);
                        let hit = accel.intersect(&shapes, &ray).map(|it| it.t);
                        assert_eq!(hit, brute, "{kernel:?}, {what}, ray {ray_index}");
                        assert_eq!(
                            accel.occluded(&shapes, &ray),
                            brute.is_some(),
                            "{kernel:?}, {what}, ray {ray_index}"
                        );
                    }
                }
                assert!(fibre_hits > 100, "{what}: {fibre_hits} rays hit a fibre first");
            }
        }
    }

    /// Transforms an instance may have: rotated, scaled unevenly, mirrored, far from the
    /// origin, squashed flat (1e-6 along z: rays from 20 units are 2e7 away in its space).
    fn placements() -> Vec<glam::Mat4> {
        use glam::{Mat4, Quat};
        vec![
            Mat4::IDENTITY,
            Mat4::from_translation(Vec3::new(12.0, -3.0, 4.0)) * Mat4::from_quat(Quat::from_rotation_y(0.7)),
            Mat4::from_translation(Vec3::new(-8.0, 6.0, 1.0))
                * Mat4::from_quat(Quat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 0.4))
                * Mat4::from_scale(Vec3::new(0.5, 2.0, 1.3)),
            Mat4::from_translation(Vec3::new(3.0, 14.0, -6.0)) * Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0)),
            Mat4::from_translation(Vec3::new(900.0, -700.0, 1300.0)) * Mat4::from_scale(Vec3::splat(0.05)),
            Mat4::from_translation(Vec3::new(-20.0, -15.0, 10.0))
                * Mat4::from_scale(Vec3::new(1.0, 1.0, 1e-6)),
        ]
    }

    /// A group placed by instances finds what copies of its shapes, transformed and placed as
    /// ordinary shapes, find: the same triangle at the same distance, point and normal, for
    /// every kernel; occlusion agrees with the closest hit.
    #[test]
    fn instances_hit_what_their_flattened_copies_hit() {
        use crate::geometry::Instance;
        let group = soup(400, 21).remove(0);
        let Geometry::Mesh(mesh) = &group.geometry else { unreachable!() };
        let bounds = (0..group.prim_count())
            .map(|k| group.prim_bounds(k))
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), (a, b)| (lo.min(a), hi.max(b)));
        let mut shapes = vec![group.clone()];
        let mut flat = Vec::new();
        for m in placements() {
            shapes.push(shape(Geometry::Instance(Instance::new(0, m, Some(bounds))), "instance"));
            let mut copy = mesh.clone();
            copy.transform(&m);
            flat.push(shape(Geometry::Mesh(copy), "copy"));
        }
        let mut accel = Accel::build_grouped(&shapes, &[vec![0]]);
        let flat_accel = Accel::build(&flat);
        assert_eq!(accel.prim_count(), placements().len());
        assert_eq!(accel.group_stats(), (1, 400));
        let mut s = 5;
        let (mut hits, mut disagree) = (0, [0; 6]);
        for (k, m) in placements().into_iter().enumerate() {
            for _ in 0..1500 {
                // Rays from around each placement towards points inside it.
                let target = m
                    .transform_point3(Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * 10.0);
                let dir = Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5;
                let scale = m.x_axis.truncate().length();
                let o = target + dir.normalize() * 20.0 * scale;
                let ray = Ray::new(o, (target - o).normalize());
                let want = flat_accel.intersect(&flat, &ray);
                for (kernel, decoded) in Kernel::available().into_iter().flat_map(|k| [(k, true), (k, false)])
                {
                    accel.set_kernel(kernel);
                    accel.set_flat(decoded);
                    let got = accel.intersect(&shapes, &ray);
                    assert_eq!(
                        accel.occluded(&shapes, &ray),
                        got.is_some(),
                        "{kernel:?}, decoded {decoded}, placement {k}"
                    );
                    match (&got, &want) {
                        (Some(g), Some(w)) => {
                            hits += 1;
                            // f32 rounding of the copies' vertices, at the placement's scale.
                            let tol = 1e-4 * (1.0 + w.t) + 1e-5 * w.p.abs().max_element();
                            if g.prim != w.prim && (g.t - w.t).abs() > tol {
                                disagree[k] += 1;
                                continue;
                            }
                            assert!((g.t - w.t).abs() <= tol, "placement {k}: t {} against {}", g.t, w.t);
                            assert!(
                                (g.p - w.p).length() <= tol * 2.0,
                                "placement {k}: p {} against {}",
                                g.p,
                                w.p
                            );
                            // The normal against the triangle's own, carried to the world in
                            // f64 by the inverse transpose of the placement it lies in (the
                            // copies' normals lose digits far from the origin, and mirrored
                            // copies turn theirs around).
                            let tri = mesh.tri(g.prim as usize).map(|v| v.as_dvec3());
                            let local = (tri[1] - tri[0]).cross(tri[2] - tri[0]);
                            let off_plane = |md: &glam::DMat4| {
                                let w = tri.map(|v| md.transform_point3(v));
                                let p = g.p.as_dvec3();
                                let slack = 1e-3 + 1e-5 * p.abs().max_element();
                                let lo = w[0].min(w[1]).min(w[2]) - slack;
                                let hi = w[0].max(w[1]).max(w[2]) + slack;
                                let n = (w[1] - w[0]).cross(w[2] - w[0]).normalize();
                                let inside = p.cmpge(lo).all() && p.cmple(hi).all();
                                if inside {
                                    (p - w[0]).dot(n).abs() / slack
                                } else {
                                    f64::INFINITY
                                }
                            };
                            let md = placements()
                                .iter()
                                .map(|m| m.as_dmat4())
                                .min_by(|a, b| off_plane(a).total_cmp(&off_plane(b)))
                                .unwrap_or_else(|| unreachable!());
                            assert!(off_plane(&md) < 1.0, "the hit lies on a placed copy of its triangle");
                            let exact =
                                (glam::DMat3::from_mat4(md.inverse()).transpose() * local).normalize();
                            assert!(
                                g.ng.as_dvec3().dot(exact) > 1.0 - 1e-6,
                                "placement {k}: ng {} against {exact}",
                                g.ng
                            );
                            assert!(
                                g.ng.dot(w.ng).abs() > 0.99,
                                "placement {k}: ng {} against the copy's {}",
                                g.ng,
                                w.ng
                            );
                            assert!(
                                g.p_err.cmpge(Vec3::ZERO).all()
                                    && (g.p - w.p).abs().cmple(g.p_err + w.p_err + tol).all()
                            );
                            assert_eq!(g.shape, 0, "hits inside an instance are its group's shape");
                        }
                        (None, None) => {}
                        _ => disagree[k] += 1, // a ray through an edge, rounded differently
                    }
                }
            }
        }
        assert!(hits > 5000, "{hits} hits");
        // Only far from the origin, where the copies' vertices are rounded to 6e-5 on
        // triangles 0.015 wide, do rays through edges go either way (21 of 6402 here).
        eprintln!("{hits} hits, disagreements by placement: {disagree:?}");
        assert_eq!(disagree[..4], [0; 4]);
        assert_eq!(disagree[5], 0, "the squashed placement");
        assert!(disagree[4] * 100 < hits, "{} of {hits} rays disagree", disagree[4]);
    }

    /// Rays leaving the surface of an instanced sphere, made an ellipsoid far from the origin,
    /// never find it again on the way out, and always find it again on the way in.
    #[test]
    fn rays_leaving_an_instanced_surface_do_not_find_it_again() {
        use crate::geometry::{Instance, Sphere};
        use glam::{Mat3, Mat4, Quat};
        let sphere = shape(
            Geometry::Sphere(Sphere { center: Vec3::ZERO, radius: 1.0, rot: Mat3::IDENTITY, tangents: true }),
            "ball",
        );
        let m = Mat4::from_translation(Vec3::new(1000.0, 2000.0, -500.0))
            * Mat4::from_quat(Quat::from_rotation_z(0.6))
            * Mat4::from_scale(Vec3::new(3.0, 0.5, 1.0));
        let inst = Instance::new(0, m, Some((Vec3::splat(-1.0), Vec3::ONE)));
        let shapes = vec![sphere, shape(Geometry::Instance(inst), "ellipsoid")];
        let accel = Accel::build_grouped(&shapes, &[vec![0]]);
        let centre = m.transform_point3(Vec3::ZERO);
        let mut s = 77;
        let (mut out, mut back) = (0, 0);
        for _ in 0..5000 {
            let dir = (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5).normalize();
            let o = centre + dir * 10.0;
            let aim =
                m.transform_point3(Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5);
            let Some(it) = accel.intersect(&shapes, &Ray::new(o, (aim - o).normalize())) else {
                panic!("a ray at the ellipsoid's middle missed it");
            };
            let d = (Vec3::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5).normalize();
            let d = if d.dot(it.ng) > 0.0 { d } else { -d };
            if d.dot(it.ng) < 1e-3 {
                continue;
            }
            if accel.intersect(&shapes, &it.spawn_ray(d)).is_some() {
                out += 1;
            }
            match accel.intersect(&shapes, &it.spawn_ray(-d)) {
                Some(h) if h.t > 1e-3 => {}
                _ => back += 1,
            }
        }
        assert_eq!((out, back), (0, 0), "rays out that hit again, rays in that missed");
    }

    /// A panel in an instance squashed 1e-9 across (the most the loader allows) is hit by
    /// every ray aimed at it from a few units away, as the same panel placed flat is: such a
    /// ray starts 1e9 times farther away in the group's space, past what a triangle's error
    /// bound accepts, unless it starts again near the group's box.
    #[test]
    fn a_squashed_instance_is_still_hit() {
        use crate::geometry::Instance;
        let panel = shape(Geometry::Mesh(Mesh::rectangle()), "panel");
        for squash in [1e-3, 1e-6, 1e-9] {
            let m = glam::Mat4::from_scale(Vec3::new(1.0, 1.0, squash));
            let inst = Instance::new(0, m, Some((Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, 1.0, 0.0))));
            let shapes = vec![panel.clone(), shape(Geometry::Instance(inst), "squashed")];
            let accel = Accel::build_grouped(&shapes, &[vec![0]]);
            let mut s = 3;
            for _ in 0..2000 {
                let aim = Vec3::new(xorshift(&mut s) * 1.9 - 0.95, xorshift(&mut s) * 1.9 - 0.95, 0.0);
                let o = Vec3::new(xorshift(&mut s) - 0.5, xorshift(&mut s) - 0.5, 1.0) * 6.0;
                let ray = Ray::new(o, (aim - o).normalize());
                let it = accel
                    .intersect(&shapes, &ray)
                    .unwrap_or_else(|| panic!("squash {squash}: missed from {o}"));
                assert!(
                    (it.p - aim).length() < 1e-5 && it.ng.z.abs() > 0.9999,
                    "squash {squash}: {} {}",
                    it.p,
                    it.ng
                );
            }
        }
    }

    /// 20,000 triangles with one box between them: the builder still gives a shallow tree,
    /// and traversal finds the closest of them, with its stack inline or on the heap (which
    /// only trees deeper than 73 levels need).
    #[test]
    fn coincident_primitives_are_all_found() {
        let mut m = Mesh::default();
        for i in 0..20_000u32 {
            // Identical boxes, slightly different depths along z.
            let z = (i % 997) as f32 * 1e-4;
            m.positions.extend([Vec3::new(0.0, 0.0, z), Vec3::new(1.0, 0.0, z), Vec3::new(0.0, 1.0, z)]);
            m.tris.push([3 * i, 3 * i + 1, 3 * i + 2]);
        }
        let shapes = vec![Shape {
            geometry: Geometry::Mesh(m),
            bsdf: 0,
            light: None,
            flip_normals: false,
            name: "stack".into(),
        }];
        let mut accel = Accel::build(&shapes);
        assert!(accel.stack_size <= INLINE_STACK, "PLOC keeps even this tree shallow: {}", accel.stack_size);
        let ray = Ray::new(Vec3::new(0.2, 0.2, 5.0), Vec3::NEG_Z);
        // Then as if the tree were deeper than the inline stack: the heap stack is used.
        for heap in [false, true] {
            if heap {
                accel.stack_size = INLINE_STACK + 1;
            }
            for kernel in Kernel::available() {
                accel.set_kernel(kernel);
                let hit = accel.intersect(&shapes, &ray).expect("a hit");
                assert!((hit.t - (5.0 - 996e-4)).abs() < 1e-4, "{kernel:?}, heap {heap}: t {}", hit.t);
                assert!(accel.occluded(&shapes, &ray));
            }
        }
    }

    /// Quantised planes enclose their child's box, for boxes far from the origin, tiny, flat
    /// and huge alike.
    #[test]
    fn quantised_boxes_enclose_their_children() {
        let mut s = 9;
        for round in 0..2000 {
            let centre = (Vec3A::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) - 0.5)
                * [1.0, 1e3, 1e6, 1e-3][round % 4];
            let n = 1 + round % WIDTH;
            let boxes: Vec<(Vec3A, Vec3A)> = (0..n)
                .map(|k| {
                    let size = [1e-6, 0.0, 1.0, 1e4][(round + k) % 4];
                    let lo = centre + Vec3A::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * size;
                    let hi = lo + Vec3A::new(xorshift(&mut s), xorshift(&mut s), xorshift(&mut s)) * size;
                    (lo, hi)
                })
                .collect();
            let node = Node::quantise(&boxes);
            assert_eq!(node.used, (1 << n) - 1);
            for (i, (lo, hi)) in boxes.iter().enumerate() {
                for a in 0..3 {
                    let plane = |p: usize| node.origin[a] + node.planes[p][i] as f32 * node.scale[a];
                    assert!(
                        plane(2 * a) <= lo[a] && plane(2 * a + 1) >= hi[a],
                        "round {round}, box {i}, axis {a}"
                    );
                }
            }
        }
    }

    /// Only the used lanes are entered, whatever the direction's signs (zeros of either sign
    /// included); a ray running inside a box's slab exactly on its plane (0 * inf) still
    /// enters it.
    #[test]
    fn unused_lanes_are_never_entered_and_planes_are_inclusive() {
        let boxes = [(Vec3A::ZERO, Vec3A::ONE), (Vec3A::splat(5.0), Vec3A::splat(6.0))];
        let node = Node::quantise(&boxes);
        for (o, d) in [
            (Vec3::new(0.0, 0.5, -3.0), Vec3::new(0.0, 0.0, 1.0)),
            (Vec3::new(1.0, 0.5, 4.0), Vec3::new(-0.0, 0.0, -1.0)),
            (Vec3::new(-3.0, 0.0, 0.5), Vec3::new(1.0, -0.0, 0.0)),
            (Vec3::new(3.0, -2.5, -2.5), Vec3::new(-1.0, 1.0, 1.0).normalize()),
        ] {
            let r = BoxRay::new(&Ray::new(o, d));
            let mut answers = vec![test_scalar(&node, &r, 0.0, f32::INFINITY).0];
            #[cfg(target_arch = "x86_64")]
            for kernel in Kernel::available() {
                // SAFETY: the kernel is available.
                let m = unsafe {
                    match kernel {
                        Kernel::Avx2 => AvxTest::test(&node, &r, 0.0, f32::INFINITY).0,
                        Kernel::Sse => SseTest::test(&node, &r, 0.0, f32::INFINITY).0,
                        Kernel::Scalar => ScalarTest::test(&node, &r, 0.0, f32::INFINITY).0,
                    }
                };
                answers.push(m);
            }
            for m in answers {
                assert_eq!(m, 1, "ray {o} + t {d}");
            }
        }
    }
}

#[cfg(test)]
mod oriented_estimate {
    use super::*;

    /// Surface area of the box around `segs` (each a capsule-ish segment bounded by its
    /// larger radius) in the frame `(x, y, z)`.
    fn area(segs: &[Segment], frame: [Vec3; 3]) -> f64 {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for s in segs {
            let r = s.r0.max(s.r1);
            for p in [s.p0, s.p0 + (s.p1 - s.p0)] {
                for a in 0..3 {
                    let x = frame[a].dot(p);
                    lo[a] = lo[a].min(x - r);
                    hi[a] = hi[a].max(x + r);
                }
            }
        }
        let e: Vec<f64> = (0..3).map(|a| (hi[a] - lo[a]) as f64).collect();
        2.0 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0])
    }

    fn oriented(segs: &[Segment]) -> f64 {
        let v = |s: &Segment| s.p1 - s.p0;
        let first = v(&segs[0]);
        let z = segs.iter().fold(Vec3::ZERO, |acc, s| acc + if v(s).dot(first) < 0.0 { -v(s) } else { v(s) });
        let z = z.normalize_or(Vec3::Z);
        let x = z.any_orthonormal_vector();
        area(segs, [x, z.cross(x), z])
    }

    fn gather(a: &Accel, shapes: &[Shape], c: u32, out: &mut Vec<Segment>) {
        if c & LEAF != 0 {
            let first = c & ((1 << FIRST_BITS) - 1);
            let count = ((c >> FIRST_BITS) & 3) + 1;
            for k in first..first + count {
                let p = a.prims[k as usize];
                if let Geometry::Curves(curves) = &shapes[(p.shape & SHAPE) as usize].geometry {
                    out.push(curves.segments[p.index as usize]);
                }
            }
        } else {
            let n = &a.nodes[c as usize];
            for lane in 0..WIDTH {
                if n.used >> lane & 1 != 0 {
                    gather(a, shapes, n.child[lane], out);
                }
            }
        }
    }

    /// A measurement for docs/BENCHMARKS.md, not a check: on hair.xml, the summed surface
    /// areas of every child box (the SAH's expected visits, up to one factor) with axis-aligned
    /// boxes and with boxes along each child's mean fibre direction (the smaller of the two),
    /// by the child's subtree size; what oriented bounds could save on obvhs' topology.
    /// `cargo test --release -p furnace-core --lib oriented_boxes_estimate -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn oriented_boxes_estimate() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/scenes/hair.xml");
        let scene = crate::scene::Scene::load(&path, &[]).expect("hair.xml");
        let a = &scene.accel;
        let mut by_size = std::collections::BTreeMap::<u32, (f64, f64, usize)>::new();
        for n in &a.nodes {
            for lane in 0..WIDTH {
                if n.used >> lane & 1 == 0 {
                    continue;
                }
                let mut segs = Vec::new();
                gather(a, &scene.shapes, n.child[lane], &mut segs);
                if segs.is_empty() {
                    continue;
                }
                let aa = area(&segs, [Vec3::X, Vec3::Y, Vec3::Z]);
                let ob = oriented(&segs).min(aa);
                let bucket = (segs.len() as u32).next_power_of_two();
                let e = by_size.entry(bucket).or_default();
                e.0 += aa;
                e.1 += ob;
                e.2 += 1;
            }
        }
        let (mut ta, mut to) = (0.0, 0.0);
        for (size, (aa, ob, n)) in &by_size {
            println!("subtree <= {size:>6} segments: {n:>6} boxes, oriented / aligned area {:.3}", ob / aa);
            ta += aa;
            to += ob;
        }
        println!("all child boxes: oriented / aligned area {:.3}", to / ta);
        assert!(ta.is_finite() && to > 0.0 && to <= ta, "areas {ta} aligned, {to} oriented");
    }
}
