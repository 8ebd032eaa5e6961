//! `furnace generate`: writes a scene of the seed's class ("Whimsical Night"): a creature-like
//! body (a binary PLY of two bumpy ellipsoids), fur of B-spline fibres grown on it with the hair
//! BSDF, a checkerboard ground, a rough aluminium ball and a plastic ball, a sun/sky map and a
//! thin-lens camera focused on the fur, 1920x1080. Its size is set by the number of fibres
//! (8 segments each) and of body triangles: `--fibres 8250000` gives the seed's 66 million
//! primitives.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Args;
use furnace_core::Image;
// glam's Vec3, through the renderer (the package does not name glam itself).
use furnace_core::math::Rgb as Vec3;

#[derive(Args)]
pub struct GenerateArgs {
    /// Folder to write scene.xml, body.ply, fur.txt and sky.exr into.
    pub dir: PathBuf,
    /// Fur fibres (one B-spline span each: 8 segments).
    #[arg(long, default_value_t = 250_000)]
    pub fibres: u64,
    /// Triangles of the body mesh (at least 200).
    #[arg(long, default_value_t = 400_000)]
    pub body_triangles: u64,
    /// Seed of the fur's random placement.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Tufts of grass on the ground: one tuft (grass.txt) in a shapegroup, placed this many
    /// times by instances (turned, scaled), so they cost the memory of one.
    #[arg(long, default_value_t = 0)]
    pub grass_tufts: u64,
    /// Blades of one tuft (one B-spline span each: 8 segments).
    #[arg(long, default_value_t = 200)]
    pub blades: u64,
}

/// An ellipsoid of the body: centre, radii, its share of the triangles and of the fibres.
struct Part {
    centre: Vec3,
    radii: Vec3,
    share: f64,
}

const PARTS: [Part; 2] = [
    Part { centre: Vec3::new(0.0, 0.85, 0.0), radii: Vec3::new(1.0, 0.72, 0.8), share: 0.8 },
    Part { centre: Vec3::new(0.95, 1.55, 0.1), radii: Vec3::new(0.48, 0.45, 0.45), share: 0.2 },
];

/// A point of a part's bumpy surface at (theta, phi), and its outward normal.
fn surface(p: &Part, theta: f64, phi: f64) -> (Vec3, Vec3) {
    let at = |t: f64, f: f64| {
        let bump = 1.0 + 0.025 * (7.0 * t).sin() * (5.0 * f).cos();
        let d = Vec3::new((t.sin() * f.cos()) as f32, t.cos() as f32, (t.sin() * f.sin()) as f32);
        p.centre + d * p.radii * bump as f32
    };
    let (e, x) = (1e-4, at(theta, phi));
    let dt = at(theta + e, phi) - at(theta - e, phi);
    let dp = at(theta, phi + e) - at(theta, phi - e);
    let mut n = dp.cross(dt).normalize_or_zero();
    if n.dot(x - p.centre) < 0.0 {
        n = -n;
    }
    (x, if n == Vec3::ZERO { (x - p.centre).normalize() } else { n })
}

pub fn generate(a: GenerateArgs) -> Result<()> {
    if a.body_triangles < 200 {
        bail!("--body-triangles must be at least 200");
    }
    if a.fibres == 0 {
        bail!("--fibres must be at least 1 (a curve file needs a curve)");
    }
    if a.fibres.saturating_mul(8) > furnace_core::geometry::bvh::MAX_PRIMS as u64 {
        bail!(
            "--fibres {}: more than a BVH holds ({} primitives)",
            a.fibres,
            furnace_core::geometry::bvh::MAX_PRIMS
        );
    }
    std::fs::create_dir_all(&a.dir).with_context(|| format!("cannot create {}", a.dir.display()))?;
    let t = std::time::Instant::now();
    let tris = write_body(&a.dir.join("body.ply"), a.body_triangles)?;
    write_fur(&a.dir.join("fur.txt"), a.fibres, a.seed)?;
    sky().write_exr(&a.dir.join("sky.exr"))?;
    let mut scene = SCENE.to_string();
    if a.grass_tufts > 0 {
        if a.blades == 0 {
            bail!("--blades must be at least 1");
        }
        write_tuft(&a.dir.join("grass.txt"), a.blades, a.seed)?;
        scene = scene.replace("</scene>", &grass(a.grass_tufts, a.seed)?);
    }
    std::fs::write(a.dir.join("scene.xml"), scene).context("cannot write scene.xml")?;
    let grass = if a.grass_tufts > 0 {
        format!(
            ", and {} tufts of {} grass blades ({} segments drawn, {} held)",
            a.grass_tufts,
            a.blades,
            a.grass_tufts.saturating_mul(a.blades * 8),
            a.blades * 8
        )
    } else {
        String::new()
    };
    println!(
        "wrote {}: {tris} body triangles and {} fibres ({} segments): {} primitives{grass}, in {:.1} s",
        a.dir.join("scene.xml").display(),
        a.fibres,
        a.fibres * 8,
        tris + a.fibres * 8 + 4,
        t.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The generator's random numbers in [0, 1), from `seed` and a stream tag.
fn rng(seed: u64, stream: u64) -> impl FnMut() -> f64 {
    let mut state = seed.wrapping_mul(0x9e3779b97f4a7c15) ^ 0x853c49e6748fea9b ^ stream;
    move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// One tuft of grass: `blades` B-spline blades rooted in a disk of radius 0.12 at the origin,
/// 0.25 to 0.4 tall, leaning outwards.
fn write_tuft(path: &Path, blades: u64, seed: u64) -> Result<()> {
    let mut next = rng(seed, 0x67726173);
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?,
    );
    for _ in 0..blades {
        let (r, a) = (0.12 * next().sqrt(), 2.0 * std::f64::consts::PI * next());
        let root = Vec3::new((r * a.cos()) as f32, 0.0, (r * a.sin()) as f32);
        let lean = Vec3::new(root.x, 0.0, root.z) * 1.5
            + Vec3::new(next() as f32 - 0.5, 0.0, next() as f32 - 0.5) * 0.2;
        let height = (0.25 + 0.15 * next()) as f32;
        for k in 0..4 {
            let t = k as f32 / 3.0;
            let p = root + Vec3::Y * (height * t) + lean * (t * t);
            writeln!(f, "{:.5} {:.5} {:.5} {:.5}", p.x, p.y, p.z, 0.004 * (1.0 - 0.8 * t))?;
        }
        writeln!(f)?;
    }
    f.flush()?;
    Ok(())
}

/// The grass group and `tufts` instances of it on the ground around the creature and the
/// balls (kept 0.3 clear of them), closing the scene.
fn grass(tufts: u64, seed: u64) -> Result<String> {
    let mut next = rng(seed, 0x74756674);
    let mut xml = String::from(
        r#"    <shape type="shapegroup" id="grass">
        <shape type="bsplinecurve"><string name="filename" value="grass.txt"/>
            <bsdf type="diffuse"><rgb name="reflectance" value="0.22, 0.42, 0.1"/></bsdf></shape>
    </shape>
"#,
    );
    let clear = [(0.0, 0.0, 1.7), (0.95, 0.1, 0.9), (-2.2, 1.0, 0.9), (2.3, 1.0, 0.8)];
    let mut placed = 0;
    while placed < tufts {
        let (x, z) = (-10.0 + 20.0 * next(), -8.0 + 15.0 * next());
        if clear.iter().any(|&(cx, cz, r)| (x - cx) * (x - cx) + (z - cz) * (z - cz) < r * r) {
            continue;
        }
        let (turn, size) = (360.0 * next(), 0.7 + 0.6 * next());
        use std::fmt::Write as _;
        writeln!(
            xml,
            r#"    <shape type="instance"><ref id="grass"/><transform name="to_world"><scale value="{size:.3}"/><rotate y="1" angle="{turn:.1}"/><translate x="{x:.4}" z="{z:.4}"/></transform></shape>"#
        )?;
        placed += 1;
    }
    xml.push_str("</scene>\n");
    Ok(xml)
}

/// The body as binary little-endian PLY; returns its triangle count.
fn write_body(path: &Path, triangles: u64) -> Result<u64> {
    let mut verts: Vec<Vec3> = Vec::new();
    let mut faces: Vec<[u32; 3]> = Vec::new();
    for p in &PARTS {
        // rings x sectors quads, two triangles each.
        let quads = (triangles as f64 * p.share / 2.0).max(50.0);
        let rings = (quads / 2.0).sqrt().round().max(5.0) as u32;
        let sectors = (quads / rings as f64).round().max(10.0) as u32;
        let base = verts.len() as u32;
        for i in 0..=rings {
            for j in 0..sectors {
                let theta = std::f64::consts::PI * i as f64 / rings as f64;
                let phi = 2.0 * std::f64::consts::PI * j as f64 / sectors as f64;
                verts.push(surface(p, theta, phi).0);
            }
        }
        for i in 0..rings {
            for j in 0..sectors {
                let k = |i: u32, j: u32| base + i * sectors + j % sectors;
                let (a, b, c, d) = (k(i, j), k(i, j + 1), k(i + 1, j), k(i + 1, j + 1));
                // Quads at the poles have a corner twice: one triangle there.
                if i > 0 {
                    faces.push([a, c, b]);
                }
                if i + 1 < rings {
                    faces.push([b, c, d]);
                }
            }
        }
    }
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?,
    );
    write!(
        f,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    )?;
    for v in &verts {
        for c in v.to_array() {
            f.write_all(&c.to_le_bytes())?;
        }
    }
    for t in &faces {
        f.write_all(&[3u8])?;
        for i in t {
            f.write_all(&(*i as i32).to_le_bytes())?;
        }
    }
    f.flush()?;
    Ok(faces.len() as u64)
}

/// Fibres rooted uniformly over the parts (by their shares), growing along the normal, drooping
/// and bending a little, tapering from 3 to 0.5 thousandths.
fn write_fur(path: &Path, fibres: u64, seed: u64) -> Result<()> {
    let mut next = rng(seed, 0);
    let mut f = std::io::BufWriter::with_capacity(
        1 << 20,
        std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?,
    );
    for _ in 0..fibres {
        let part = if next() < PARTS[0].share { &PARTS[0] } else { &PARTS[1] };
        // Uniform on the (unbumped) sphere of directions: cos theta uniform.
        let theta = (1.0 - 2.0 * next()).acos();
        let phi = 2.0 * std::f64::consts::PI * next();
        let (root, n) = surface(part, theta, phi);
        let len = (0.10 + 0.06 * next()) as f32;
        let bend = Vec3::new(next() as f32 - 0.5, next() as f32 - 0.5, next() as f32 - 0.5) * 0.5;
        for k in 0..4 {
            let t = k as f32 / 3.0;
            let p = root + n * (len * t) + (bend - Vec3::Y * 0.6) * (len * t * t * 0.5);
            writeln!(f, "{:.5} {:.5} {:.5} {:.5}", p.x, p.y, p.z, 0.003 * (1.0 - 0.83 * t))?;
        }
        writeln!(f)?;
    }
    f.flush()?;
    Ok(())
}

/// A 1024 x 512 lat-long sun/sky map (Mitsuba's convention): a sun 0.5 degrees across of
/// radiance 1e5, 25 degrees up, a blue-to-pale sky and a dark ground; 4 x 4 points a texel.
fn sky() -> Image {
    let (w, h, ss) = (1024u32, 512u32, 4u32);
    let sun = Vec3::new(0.45, 25f32.to_radians().sin(), 0.75).normalize();
    let cos_sun = 0.25f32.to_radians().cos();
    let mut data = Vec::with_capacity((w * h) as usize);
    for j in 0..h {
        for i in 0..w {
            let mut c = Vec3::ZERO;
            for sj in 0..ss {
                for si in 0..ss {
                    let u = (i as f32 + (si as f32 + 0.5) / ss as f32) / w as f32;
                    let v = (j as f32 + (sj as f32 + 0.5) / ss as f32) / h as f32;
                    let (theta, phi) = (std::f32::consts::PI * v, 2.0 * std::f32::consts::PI * u);
                    let d = Vec3::new(theta.sin() * phi.sin(), theta.cos(), -theta.sin() * phi.cos());
                    c += if d.dot(sun) >= cos_sun {
                        Vec3::new(1.0e5, 0.96e5, 0.88e5)
                    } else if d.y > 0.0 {
                        let t = d.y.sqrt();
                        Vec3::new(0.45, 0.5, 0.55) * (1.0 - t) + Vec3::new(0.10, 0.18, 0.40) * t
                    } else {
                        Vec3::new(0.08, 0.07, 0.06)
                    };
                }
            }
            data.push(c / (ss * ss) as f32);
        }
    }
    Image { width: w, height: h, data }
}

const SCENE: &str = r#"<?xml version="1.0" encoding="utf-8"?>
<!-- Written by `furnace generate`: a furry creature (body.ply, fur.txt with the hair BSDF) on a
     checkerboard ground beside a rough aluminium ball and a plastic ball, lit by a sun/sky map
     (sky.exr), seen through a thin lens focused on the fur. -->
<scene version="3.0.0">
    <default name="spp" value="64"/>
    <default name="width" value="1920"/>
    <default name="height" value="1080"/>
    <integrator type="path"><integer name="max_depth" value="8"/></integrator>
    <sensor type="thinlens">
        <float name="fov" value="35"/>
        <float name="aperture_radius" value="0.04"/>
        <float name="focus_distance" value="7.8"/>
        <transform name="to_world"><lookat origin="0.2, 1.9, 8.5" target="0.2, 0.9, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="$width"/><integer name="height" value="$height"/>
            <rfilter type="box"/></film>
    </sensor>
    <emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>
    <shape type="ply"><string name="filename" value="body.ply"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.45, 0.3, 0.18"/></bsdf></shape>
    <shape type="bsplinecurve"><string name="filename" value="fur.txt"/>
        <bsdf type="hair"><float name="eumelanin" value="0.05"/><float name="pheomelanin" value="0.25"/></bsdf></shape>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="12"/></transform>
        <bsdf type="diffuse"><texture type="checkerboard" name="reflectance">
            <rgb name="color0" value="0.2, 0.35, 0.15"/><rgb name="color1" value="0.35, 0.5, 0.25"/>
            <transform name="to_uv"><scale x="24" y="24"/></transform></texture></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="-2.2" y="0.6" z="1.0"/><float name="radius" value="0.6"/>
        <!-- aluminium, RGB approximations -->
        <bsdf type="roughconductor"><string name="distribution" value="ggx"/><float name="alpha" value="0.05"/>
            <rgb name="eta" value="1.657, 0.880, 0.521"/><rgb name="k" value="9.224, 6.270, 4.837"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="2.3" y="0.5" z="1.0"/><float name="radius" value="0.5"/>
        <bsdf type="plastic"><rgb name="diffuse_reflectance" value="0.8, 0.12, 0.1"/></bsdf>
    </shape>
</scene>
"#;
