//! Triangle meshes: OBJ (tobj) and PLY (ply-rs-bw) loading, and Mitsuba's `rectangle` and `cube`.

use std::path::Path;

use glam::{Mat4, Vec2, Vec3, Vec3A};

use crate::math::{gamma, Frame};

/// A world-space triangle mesh. `normals` and `uvs` are either empty or one per vertex.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    pub normals: Vec<Vec3>,
    pub uvs: Vec<Vec2>,
    pub tris: Vec<[u32; 3]>,
    /// For a small flat-shaded mesh (no vertex normals, at most [`FACES_MAX`] triangles), what
    /// [`Mesh::surface`] computes the same for every point of a triangle, computed once
    /// ([`Mesh::precompute_faces`]); empty otherwise.
    pub faces: Vec<Face>,
    /// For Mitsuba's `rectangle`: its corner at uv (0, 0) and its edges towards uv (1, 0) and
    /// (0, 1), so that an area light on it samples the parallelogram as a whole.
    pub parallelogram: Option<[Vec3; 3]>,
}

/// Triangles up to which a flat-shaded mesh keeps its [`Face`]s (108 bytes a triangle).
pub const FACES_MAX: usize = 1024;

/// A flat-shaded triangle's constants: its unit normal, dp/du and dp/dv, and its shading
/// frame with the normal as it is and flipped (`flip_normals`), each as
/// [`Frame::from_normal_tangent`] makes it, so a hit's interaction has the same bits either way.
#[derive(Clone, Copy, Debug)]
pub struct Face {
    pub ng: Vec3,
    pub dpdu: Vec3,
    pub dpdv: Vec3,
    pub frames: [Frame; 2],
}

/// Why a mesh file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("cannot read mesh: {0}")]
    Io(#[from] std::io::Error),
    #[error("cannot parse mesh: {0}")]
    Parse(String),
    #[error("mesh has no triangles")]
    Empty,
    #[error("face {face} refers to vertex {index}, but the mesh has {count} vertices")]
    BadIndex { face: usize, index: u32, count: usize },
    #[error("vertex {0} has a non-finite coordinate")]
    NonFinite(usize),
    #[error("vertex {index}'s {what} is {value} (it must be finite{})", if *what == "normal" { " and non-zero; face_normals=true ignores the file's normals" } else { "" })]
    BadAttribute { index: usize, what: &'static str, value: String },
}

impl Mesh {
    #[inline]
    pub fn tri(&self, i: usize) -> [Vec3; 3] {
        let [a, b, c] = self.tris[i];
        [self.positions[a as usize], self.positions[b as usize], self.positions[c as usize]]
    }

    /// Point, error bound, geometric normal, shading normal, uv, dp/du and dp/dv at barycentrics
    /// (b1, b2) of triangle `i`. Without texture coordinates uv = (b1, b2), as in Mitsuba.
    /// Always inlined: a light sample reads only the point, its normal and uv, and what it
    /// does not read (dp/du, dp/dv, the geometric normal) is then never computed.
    #[inline(always)]
    pub fn surface(&self, i: usize, b1: f32, b2: f32) -> (Vec3, Vec3, Vec3, Vec3, Vec2, Vec3, Vec3) {
        // In Vec3A (SIMD lanes): lane for lane the same operations as Vec3's, so the same bits,
        // in fewer instructions than Vec3's shuffling. (A build with FMA enabled globally would
        // fuse Vec3A's cross product and change its last bit.)
        let ([ia, ib, ic], [p0, p1, p2]) = self.corners(i);
        let (p, p_err, uv) = self.point_uv_at([ia, ib, ic], [p0, p1, p2], b1, b2);
        let b0 = 1.0 - b1 - b2;
        let e1 = p1 - p0;
        let e2 = p2 - p0;
        let mut ng = e1.cross(e2).normalize_or_zero();
        let (dpdu, dpdv) = if self.uvs.is_empty() {
            (e1, e2)
        } else {
            let (t0, t1, t2) = (self.uvs[ia], self.uvs[ib], self.uvs[ic]);
            let (d1, d2) = (t1 - t0, t2 - t0);
            let det = d1.x * d2.y - d1.y * d2.x;
            if det.abs() > 1e-12 {
                ((e1 * d2.y - e2 * d1.y) / det, (e2 * d1.x - e1 * d2.x) / det)
            } else {
                (e1, e2)
            }
        };
        let ns = if self.normals.is_empty() {
            ng
        } else {
            let n = (Vec3A::from(self.normals[ia]) * b0
                + Vec3A::from(self.normals[ib]) * b1
                + Vec3A::from(self.normals[ic]) * b2)
                .normalize_or_zero();
            if n == Vec3A::ZERO {
                ng
            } else {
                // The geometric normal lies on the side of the shading normal.
                if ng.dot(n) < 0.0 {
                    ng = -ng;
                }
                n
            }
        };
        (p.into(), p_err.into(), ng.into(), ns.into(), uv, dpdu.into(), dpdv.into())
    }

    /// Point, error bound and uv at barycentrics (b1, b2) of triangle `i`, as
    /// [`Mesh::surface`] computes them.
    #[inline(always)]
    pub fn point_uv(&self, i: usize, b1: f32, b2: f32) -> (Vec3, Vec3, Vec2) {
        let (index, p) = self.corners(i);
        let (p, p_err, uv) = self.point_uv_at(index, p, b1, b2);
        (p.into(), p_err.into(), uv)
    }

    /// Triangle `i`'s vertex indices and positions.
    #[inline(always)]
    fn corners(&self, i: usize) -> ([usize; 3], [Vec3A; 3]) {
        let index = self.tris[i].map(|k| k as usize);
        (index, index.map(|k| Vec3A::from(self.positions[k])))
    }

    /// [`Mesh::point_uv`] of the triangle with vertices `index` at `p`.
    #[inline(always)]
    fn point_uv_at(&self, index: [usize; 3], p: [Vec3A; 3], b1: f32, b2: f32) -> (Vec3A, Vec3A, Vec2) {
        let [p0, p1, p2] = p;
        let b0 = 1.0 - b1 - b2;
        let p = p0 * b0 + p1 * b1 + p2 * b2;
        let p_err = ((p0 * b0).abs() + (p1 * b1).abs() + (p2 * b2).abs()) * gamma(7);
        let uv = if self.uvs.is_empty() {
            Vec2::new(b1, b2)
        } else {
            let [ia, ib, ic] = index;
            self.uvs[ia] * b0 + self.uvs[ib] * b1 + self.uvs[ic] * b2
        };
        (p, p_err, uv)
    }

    /// Computes [`Mesh::faces`] if the mesh is flat-shaded and small; call it once the mesh is
    /// in place (after its transform). Returns the bytes the faces take.
    pub fn precompute_faces(&mut self) -> usize {
        self.faces = Vec::new();
        if !self.normals.is_empty() || self.tris.len() > FACES_MAX {
            return 0;
        }
        self.faces = (0..self.tris.len())
            .map(|i| {
                // Without vertex normals the shading normal is the geometric one, and neither
                // it nor dp/du, dp/dv depends on where in the triangle the point lies.
                let (_, _, ng, ns, _, dpdu, dpdv) = self.surface(i, 0.0, 0.0);
                let frames = [Frame::from_normal_tangent(ns, dpdu), Frame::from_normal_tangent(-ns, dpdu)];
                Face { ng, dpdu, dpdv, frames }
            })
            .collect();
        std::mem::size_of_val(self.faces.as_slice())
    }

    /// Applies `to_world` to positions and (by the inverse transpose) to normals. Drops the
    /// faces and the parallelogram, which no longer hold (compute them again once placed).
    pub fn transform(&mut self, m: &Mat4) {
        self.faces = Vec::new();
        self.parallelogram = None;
        for p in &mut self.positions {
            *p = m.transform_point3(*p);
        }
        let nm = m.inverse().transpose();
        for n in &mut self.normals {
            *n = nm.transform_vector3(*n).normalize_or_zero();
        }
    }

    /// Checks indices and coordinates, and drops degenerate (zero-area) triangles (and the
    /// faces and parallelogram, which then no longer hold).
    pub fn validate(mut self) -> Result<Mesh, MeshError> {
        self.faces = Vec::new();
        self.parallelogram = None;
        let count = self.positions.len();
        if let Some(k) = self.positions.iter().position(|p| !p.is_finite()) {
            return Err(MeshError::NonFinite(k));
        }
        if let Some(k) = self.normals.iter().position(|n| !n.is_finite() || n.length_squared() == 0.0) {
            let value = format!("{:?}", self.normals[k]);
            return Err(MeshError::BadAttribute { index: k, what: "normal", value });
        }
        if let Some(k) = self.uvs.iter().position(|t| !t.is_finite()) {
            let value = format!("{:?}", self.uvs[k]);
            return Err(MeshError::BadAttribute { index: k, what: "texture coordinate", value });
        }
        for (what, n) in [("normals", self.normals.len()), ("texture coordinates", self.uvs.len())] {
            if n != 0 && n != count {
                return Err(MeshError::Parse(format!("{n} {what} for {count} vertices")));
            }
        }
        for (face, t) in self.tris.iter().enumerate() {
            if let Some(&index) = t.iter().find(|&&k| k as usize >= count) {
                return Err(MeshError::BadIndex { face, index, count });
            }
        }
        let positions = &self.positions;
        self.tris.retain(|t| {
            let [a, b, c] = t.map(|k| positions[k as usize]);
            (b - a).cross(c - a).length_squared() > 0.0
        });
        if self.tris.is_empty() {
            return Err(MeshError::Empty);
        }
        Ok(self)
    }

    /// Mitsuba's `rectangle` and `cube` are flat-shaded, so they carry no vertex normals: the
    /// face normal follows the winding. A mirroring `to_world` (negative determinant) would turn
    /// it inside out, so the winding is reversed then, keeping normals where Mitsuba has them
    /// (the inverse-transpose image of the object normal).
    pub fn transform_flat(&mut self, m: &Mat4) {
        self.transform(m);
        if m.determinant() < 0.0 {
            for t in &mut self.tris {
                t.swap(1, 2);
            }
        }
    }

    /// Mitsuba's `rectangle`: [-1, 1]^2 in the xy-plane, normal +z, uv = ((x + 1) / 2, (y + 1) / 2).
    pub fn rectangle() -> Mesh {
        Mesh {
            positions: vec![
                Vec3::new(-1.0, -1.0, 0.0),
                Vec3::new(1.0, -1.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(-1.0, 1.0, 0.0),
            ],
            normals: Vec::new(),
            uvs: vec![Vec2::new(0.0, 0.0), Vec2::new(1.0, 0.0), Vec2::new(1.0, 1.0), Vec2::new(0.0, 1.0)],
            tris: vec![[0, 1, 2], [0, 2, 3]],
            faces: Vec::new(),
            parallelogram: None,
        }
    }

    /// Mitsuba's `rectangle` placed by `to_world`, with its faces and its parallelogram.
    pub fn placed_rectangle(to_world: &Mat4) -> Mesh {
        let mut m = Mesh::rectangle();
        m.transform_flat(to_world);
        m.precompute_faces();
        let p = &m.positions;
        m.parallelogram = Some([p[0], p[1] - p[0], p[3] - p[0]]);
        m
    }

    /// Mitsuba's `cube`: [-1, 1]^3, 24 vertices so that each face has its own normal and uvs.
    pub fn cube() -> Mesh {
        // Mitsuba 3's cube as it lays it out (read from `mi.load_dict({'type': 'cube'})`): per
        // face (-y, +y, +x, +z, -x, -z) four corners with their uv, two triangles (0 1 2, 3 0 2),
        // so that textures land on each face as they do there.
        #[rustfmt::skip]
        const CORNERS: [([f32; 3], [f32; 2]); 24] = [
            ([1., -1., -1.], [0., 1.]), ([1., -1., 1.], [1., 1.]), ([-1., -1., 1.], [1., 0.]), ([-1., -1., -1.], [0., 0.]),
            ([1., 1., -1.], [0., 1.]), ([-1., 1., -1.], [1., 1.]), ([-1., 1., 1.], [1., 0.]), ([1., 1., 1.], [0., 0.]),
            ([1., -1., -1.], [0., 1.]), ([1., 1., -1.], [1., 1.]), ([1., 1., 1.], [1., 0.]), ([1., -1., 1.], [0., 0.]),
            ([1., -1., 1.], [0., 1.]), ([1., 1., 1.], [1., 1.]), ([-1., 1., 1.], [1., 0.]), ([-1., -1., 1.], [0., 0.]),
            ([-1., -1., 1.], [0., 1.]), ([-1., 1., 1.], [1., 1.]), ([-1., 1., -1.], [1., 0.]), ([-1., -1., -1.], [0., 0.]),
            ([1., 1., -1.], [0., 1.]), ([1., -1., -1.], [1., 1.]), ([-1., -1., -1.], [1., 0.]), ([-1., 1., -1.], [0., 0.]),
        ];
        let mut m = Mesh::default();
        for (p, uv) in CORNERS {
            m.positions.push(Vec3::from(p));
            m.uvs.push(Vec2::from(uv));
        }
        for face in 0..6u32 {
            let b = 4 * face;
            m.tris.push([b, b + 1, b + 2]);
            m.tris.push([b + 3, b, b + 2]);
        }
        m
    }

    /// Loads a Wavefront OBJ (all objects merged). `flip_v` flips texture v, as Mitsuba does by
    /// default (`flip_tex_coords`).
    pub fn load_obj(path: &Path, flip_v: bool) -> Result<Mesh, MeshError> {
        let mut f = std::io::BufReader::new(std::fs::File::open(path)?);
        Mesh::parse_obj(&mut f, flip_v)
    }

    /// Parses OBJ text (materials are not read: Furnace takes materials from the scene).
    pub fn parse_obj(reader: &mut impl std::io::BufRead, flip_v: bool) -> Result<Mesh, MeshError> {
        let mut text = Vec::new();
        reader.read_to_end(&mut text)?;
        // tobj 4.0.5 turns face indices into offsets unchecked (it overflows on
        // `f 1/188888888888888` and on a relative `2/-9` with fewer than 9 texture
        // coordinates): check every index against what the file has defined so far.
        let lines = text.split(|&b| b == b'\n').count() as u64;
        let mut defined = [0u64; 3]; // v, vt, vn
        for (k, line) in text.split(|&b| b == b'\n').enumerate() {
            let line = String::from_utf8_lossy(line);
            // Words as tobj splits them (Unicode whitespace: a vertical tab separates too).
            let mut words = line.split_whitespace();
            match words.next() {
                Some("v") => defined[0] += 1,
                Some("vt") => defined[1] += 1,
                Some("vn") => defined[2] += 1,
                Some("f" | "l" | "p") => {
                    for word in words {
                        for (slot, i) in word.split('/').enumerate().take(3) {
                            let Ok(index) = i.parse::<i64>() else { continue };
                            let bad = if index < 0 {
                                index.unsigned_abs() > defined[slot]
                            } else {
                                index as u64 > lines
                            };
                            if bad {
                                return Err(MeshError::Parse(format!(
                                    "line {}: index {index} refers to no {}",
                                    k + 1,
                                    ["vertex", "texture coordinate", "normal"][slot]
                                )));
                            }
                        }
                    }
                }
                _ => {}
            }
        }
        let reader = &mut text.as_slice();
        let opts = tobj::LoadOptions { triangulate: true, single_index: true, ..Default::default() };
        let no_materials = |_: &Path| Ok((Vec::new(), Default::default()));
        let (models, _) =
            tobj::load_obj_buf(reader, &opts, no_materials).map_err(|e| MeshError::Parse(e.to_string()))?;
        let mut out = Mesh::default();
        let all_n = models.iter().all(|m| !m.mesh.normals.is_empty());
        let all_uv = models.iter().all(|m| !m.mesh.texcoords.is_empty());
        for model in &models {
            let mesh = &model.mesh;
            let base = out.positions.len() as u32;
            out.positions.extend(mesh.positions.chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])));
            if all_n {
                out.normals.extend(mesh.normals.chunks_exact(3).map(|n| Vec3::new(n[0], n[1], n[2])));
            }
            if all_uv {
                out.uvs.extend(
                    mesh.texcoords
                        .chunks_exact(2)
                        .map(|t| Vec2::new(t[0], if flip_v { 1.0 - t[1] } else { t[1] })),
                );
            }
            out.tris.extend(mesh.indices.chunks_exact(3).map(|t| [t[0] + base, t[1] + base, t[2] + base]));
        }
        Ok(out)
    }

    /// Loads a PLY file (ASCII or binary): `x y z`, optional `nx ny nz` and `u v` (or `s t`),
    /// faces from `vertex_indices` (or `vertex_index`), polygons fan-triangulated.
    pub fn load_ply(path: &Path) -> Result<Mesh, MeshError> {
        let mut f = std::io::BufReader::new(std::fs::File::open(path)?);
        Mesh::parse_ply(&mut f)
    }

    /// Parses a PLY file's bytes (see [`Mesh::load_ply`]). Vertices and faces are read into
    /// small typed records (not a map per element), other elements are read and dropped.
    pub fn parse_ply(f: &mut impl std::io::BufRead) -> Result<Mesh, MeshError> {
        use ply_rs_bw::parser::{Parser, Reader};
        let mut bytes = Vec::new();
        f.read_to_end(&mut bytes)?;
        check_ply_counts(&bytes)?;
        let parse = |e: ply_rs_bw::parser::ParseError| MeshError::Parse(e.to_string());
        let mut reader = Reader::new(bytes.as_slice());
        let header = Parser::<PlySkip>::new().read_header(&mut reader).map_err(parse)?;
        let (mut verts, mut faces) = (None, None);
        for (name, def) in &header.elements {
            match name.as_str() {
                "vertex" => {
                    let p = Parser::<PlyVertex>::new();
                    verts = Some(p.read_payload_for_element(&mut reader, def, &header).map_err(parse)?);
                }
                "face" => {
                    let p = Parser::<PlyFace>::new();
                    faces = Some(p.read_payload_for_element(&mut reader, def, &header).map_err(parse)?);
                }
                _ => drop(
                    Parser::<PlySkip>::new()
                        .read_payload_for_element(&mut reader, def, &header)
                        .map_err(parse)?,
                ),
            }
        }
        drop(bytes);
        let verts = verts.ok_or_else(|| MeshError::Parse("no 'vertex' element".into()))?;
        let faces = faces.ok_or_else(|| MeshError::Parse("no 'face' element".into()))?;
        let mut out = Mesh::default();
        let all = |v: &PlyVertex, slots: std::ops::Range<usize>| slots.clone().all(|k| v.rank[k] != 0);
        let (normals, uvs) = (verts.iter().all(|v| all(v, 3..6)), verts.iter().all(|v| all(v, 6..8)));
        out.positions.reserve_exact(verts.len());
        for (k, v) in verts.iter().enumerate() {
            if !all(v, 0..3) {
                return Err(MeshError::Parse(format!("vertex {k} lacks x, y or z")));
            }
            out.positions.push(Vec3::new(v.value[0], v.value[1], v.value[2]));
            if normals {
                out.normals.push(Vec3::new(v.value[3], v.value[4], v.value[5]));
            }
            if uvs {
                out.uvs.push(Vec2::new(v.value[6], v.value[7]));
            }
        }
        drop(verts);
        for (k, f) in faces.iter().enumerate() {
            let idx = f
                .indices
                .as_deref()
                .ok_or_else(|| MeshError::Parse(format!("face {k} has no vertex_indices list")))?;
            for j in 1..idx.len().saturating_sub(1) {
                out.tris.push([idx[0], idx[j], idx[j + 1]]);
            }
        }
        Ok(out)
    }
}

/// What [`Mesh::load_ply`] holds at most while it parses the file at `path`, estimated from
/// its header and size: the file, the vertex and face records (their vectors may grow to twice
/// their count), and each face's index list (at most 4 bytes an index for every byte of file,
/// plus an allocation's overhead). Measured: 3.9 (binary) and 2.8 (text) bytes per byte of file
/// for 1M vertices and 2M triangles, where this estimates 10.
pub fn ply_load_estimate(path: &Path) -> u64 {
    use std::io::{BufRead, Read};
    let size = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    let (mut verts, mut faces) = (0u64, 0u64);
    if let Ok(f) = std::fs::File::open(path) {
        // The header is text, at most a megabyte here (the parser's own limits refuse more).
        for line in std::io::BufReader::new(f).take(1 << 20).split(b'\n').map_while(Result::ok) {
            let line = String::from_utf8_lossy(&line);
            let mut words = line.split_whitespace();
            match (words.next(), words.next(), words.next().and_then(|c| c.parse::<u64>().ok())) {
                (Some("end_header"), ..) => break,
                (Some("element"), Some("vertex"), Some(n)) => verts = n,
                (Some("element"), Some("face"), Some(n)) => faces = n,
                _ => {}
            }
        }
    }
    // Counts the file cannot hold are refused before anything is allocated for them.
    let (verts, faces) = (verts.min(size), faces.min(size));
    let records =
        verts * std::mem::size_of::<PlyVertex>() as u64 + faces * std::mem::size_of::<PlyFace>() as u64;
    size.saturating_add(2 * records).saturating_add(faces * 16).saturating_add(4 * size)
}

/// The names a PLY vertex's properties may have, by slot (x, y, z, nx, ny, nz, u, v): the
/// first name of a slot's list wins over the later ones.
const PLY_VERTEX: [&[&str]; 8] =
    [&["x"], &["y"], &["z"], &["nx"], &["ny"], &["nz"], &["u", "s", "texture_u"], &["v", "t", "texture_v"]];

/// A PLY vertex as read: each slot's value, and the rank of the name it came by (0: absent).
#[derive(Default)]
struct PlyVertex {
    value: [f32; 8],
    rank: [u8; 8],
}

impl ply_rs_bw::ply::PropertyAccess for PlyVertex {
    fn new() -> Self {
        PlyVertex::default()
    }
    fn set_property(
        &mut self,
        name: &str,
        p: ply_rs_bw::ply::Property,
    ) -> ply_rs_bw::ply::PropertyAccessResult {
        use ply_rs_bw::ply::PropertyAccessResult::{Ignored, Set};
        for (k, names) in PLY_VERTEX.iter().enumerate() {
            let Some(r) = names.iter().position(|n| *n == name) else { continue };
            let rank = names.len() as u8 - r as u8;
            match p.to_f32_lossy() {
                Some(x) if rank > self.rank[k] => (self.value[k], self.rank[k]) = (x, rank),
                _ => {}
            }
            return Set;
        }
        Ignored
    }
}

/// A PLY face as read: its vertex indices (`vertex_indices`, else `vertex_index`).
#[derive(Default)]
struct PlyFace {
    indices: Option<Box<[u32]>>,
    /// Whether they came by `vertex_indices`.
    preferred: bool,
}

impl ply_rs_bw::ply::PropertyAccess for PlyFace {
    fn new() -> Self {
        PlyFace::default()
    }
    fn set_property(
        &mut self,
        name: &str,
        p: ply_rs_bw::ply::Property,
    ) -> ply_rs_bw::ply::PropertyAccessResult {
        use ply_rs_bw::ply::PropertyAccessResult::{Ignored, Set};
        let preferred = match name {
            "vertex_indices" => true,
            "vertex_index" if !self.preferred => false,
            _ => return Ignored,
        };
        if let Some(list) = p.to_u32_list() {
            self.indices = Some(list.into_boxed_slice());
            self.preferred = preferred;
        }
        Set
    }
}

/// An element Furnace does not read.
struct PlySkip;

impl ply_rs_bw::ply::PropertyAccess for PlySkip {
    fn new() -> Self {
        PlySkip
    }
}

/// Refuses a PLY header whose element counts the file cannot hold (every element takes at
/// least a byte after the header), before the parser allocates for them.
fn check_ply_counts(bytes: &[u8]) -> Result<(), MeshError> {
    const END: &[u8] = b"end_header";
    let Some(end) = bytes.windows(END.len()).position(|w| w == END) else {
        return Ok(()); // not a PLY header: the parser says so
    };
    let body = (bytes.len() - end - END.len()) as u64;
    for line in String::from_utf8_lossy(&bytes[..end]).lines() {
        let mut words = line.split_whitespace();
        if words.next() != Some("element") {
            continue;
        }
        let name = words.next().unwrap_or("");
        if let Some(count) = words.next().and_then(|c| c.parse::<u64>().ok()) {
            if count > body {
                return Err(MeshError::Parse(format!(
                    "the header declares {count} '{name}' elements; the file holds {body} bytes after it"
                )));
            }
        }
    }
    Ok(())
}

// Scene loading: the mesh shapes.
use crate::scene::build::{Builder, R};

/// `rectangle` and `cube`, placed by `to_world`.
pub(crate) fn builtin_from(b: &mut Builder, i: usize, to_world: &Mat4) -> R<super::Geometry> {
    let o = b.doc.obj(i);
    let m = if o.plugin == "cube" {
        let mut m = Mesh::cube();
        m.transform_flat(to_world);
        m.precompute_faces();
        m
    } else {
        Mesh::placed_rectangle(to_world)
    };
    // A built-in mesh's own few vertices are left to the scene text's and the BVH's charges;
    // its faces (108 bytes a triangle) are twice its size, so they are charged.
    let faces = std::mem::size_of_val(m.faces.as_slice()) as u64;
    b.budget.charge(o.plugin.as_str(), 0, faces).map_err(|e| b.err(o.pos, e))?;
    Ok(super::Geometry::Mesh(m))
}

/// `obj` (`filename`, `face_normals`, `flip_tex_coords` = true) and `ply` (`filename`,
/// `face_normals`), placed by `to_world`; refused before parsing when it would not fit.
pub(crate) fn file_from(b: &mut Builder, i: usize, to_world: &Mat4) -> R<super::Geometry> {
    let doc = b.doc;
    let o = doc.obj(i);
    let rel =
        doc.string(i, "filename")?.ok_or_else(|| b.err(o.pos, format!("{} needs a 'filename'", o.plugin)))?;
    let fpos = doc.pos_of(i, "filename");
    let path = doc.resolve_path(fpos, &rel)?;
    let face_normals = doc.boolean_or(i, "face_normals", false)?;
    let parse = if o.plugin == "ply" {
        ply_load_estimate(&path)
    } else {
        crate::scene::build::file_size(&path).saturating_mul(crate::scene::build::PARSE_PER_BYTE)
    };
    b.budget.charge(&format!("mesh '{rel}'"), parse, 0).map_err(|e| b.err(fpos, e))?;
    let obj = o.plugin == "obj";
    let flip_v = obj && doc.boolean_or(i, "flip_tex_coords", true)?;
    let load =
        || if obj { Mesh::load_obj(&path, flip_v) } else { Mesh::load_ply(&path) }.and_then(Mesh::validate);
    let what = format!("{} flip_v={flip_v}", o.plugin);
    let m = b.cached(&path, &what, load).map_err(|e| b.err(fpos, format!("{} '{rel}': {e}", o.plugin)))?;
    // The parsed mesh, in its own space; this scene's copy is placed by to_world.
    let mut m = std::sync::Arc::try_unwrap(m).unwrap_or_else(|m| (*m).clone());
    if face_normals {
        m.normals.clear();
        m.normals.shrink_to_fit();
    }
    let kept = std::mem::size_of_val(m.positions.as_slice())
        + std::mem::size_of_val(m.normals.as_slice())
        + std::mem::size_of_val(m.uvs.as_slice())
        + std::mem::size_of_val(m.tris.as_slice());
    b.budget.charge(&format!("mesh '{rel}'"), 0, kept as u64).map_err(|e| b.err(fpos, e))?;
    b.assets.push(path);
    m.transform(to_world);
    let faces = m.precompute_faces();
    b.budget.charge(&format!("mesh '{rel}'"), 0, faces as u64).map_err(|e| b.err(fpos, e))?;
    Ok(super::Geometry::Mesh(m))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cube_faces_point_outward() {
        let m = Mesh::cube();
        for i in 0..m.tris.len() {
            let (p, _, ng, ns, _, _, _) = m.surface(i, 1.0 / 3.0, 1.0 / 3.0);
            assert!(ng.dot(p) > 0.0 && (ng - ns).length() < 1e-6, "face {i}");
        }
        let mut mirrored = Mesh::cube();
        mirrored.transform_flat(&Mat4::from_scale(Vec3::new(-1.0, 2.0, 1.0)));
        for i in 0..mirrored.tris.len() {
            let (p, _, ng, _, _, _, _) = mirrored.surface(i, 1.0 / 3.0, 1.0 / 3.0);
            assert!(ng.dot(p) > 0.0, "mirrored face {i} points inward");
        }
    }

    #[test]
    fn rectangle_faces_plus_z() {
        let m = Mesh::rectangle();
        let (_, _, ng, _, uv, _, _) = m.surface(0, 0.0, 0.0);
        assert!((ng - Vec3::Z).length() < 1e-6);
        assert_eq!(uv, Vec2::new(0.0, 0.0));
    }
}
