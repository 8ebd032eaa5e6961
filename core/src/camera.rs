//! Mitsuba's `perspective` and `thinlens` sensors.
//!
//! Camera space: +z forward, +y up, +x towards the image's left (Mitsuba's `lookat`).
//! Near and far clipping are planes at camera-space z = near / far, as in Mitsuba.
//! The thin lens focuses on the plane z = `focus_distance` and samples the aperture uniformly
//! (concentric map) without a vignetting weight, again as Mitsuba does.

use glam::{DMat3, DVec2, DVec3, Mat4, Vec2, Vec3};

use crate::geometry::bvh::Bundle;
use crate::geometry::Ray;
use crate::math::square_to_uniform_disk_concentric;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThinLens {
    pub aperture_radius: f32,
    pub focus_distance: f32,
}

#[derive(Clone, Debug)]
pub struct Camera {
    pub to_world: Mat4,
    /// Full film size in pixels (before cropping).
    pub film_size: (u32, u32),
    /// tan of the half field of view along x and y.
    pub tan_half: Vec2,
    pub near_clip: f32,
    pub far_clip: f32,
    /// `None`: a pinhole. The plan drops a thin lens of zero aperture to a pinhole.
    pub lens: Option<ThinLens>,
}

impl Camera {
    /// Camera-space direction (z = 1, not normalised) through film position `pos` (pixels).
    #[inline]
    fn film_dir(&self, pos: Vec2) -> Vec3 {
        let (w, h) = self.film_size;
        let nx = 2.0 * pos.x / w as f32 - 1.0;
        let ny = 2.0 * pos.y / h as f32 - 1.0;
        Vec3::new(-nx * self.tan_half.x, -ny * self.tan_half.y, 1.0)
    }

    /// Pinhole ray through film position `pos` (in pixels of the full film).
    #[inline]
    pub fn ray_pinhole(&self, pos: Vec2) -> Ray {
        self.finish(Vec3::ZERO, self.film_dir(pos))
    }

    /// Thin-lens ray through film position `pos`, lens sample `u` in [0,1)^2.
    #[inline]
    pub fn ray_thin_lens(&self, lens: &ThinLens, pos: Vec2, u: Vec2) -> Ray {
        let focus = self.film_dir(pos) * lens.focus_distance;
        let l = square_to_uniform_disk_concentric(u) * lens.aperture_radius;
        let o = Vec3::new(l.x, l.y, 0.0);
        self.finish(o, focus - o)
    }

    /// [`Camera::ray_pinhole`] or [`Camera::ray_thin_lens`] (with lens samples `lens_u`) for
    /// each of `pos` (at most eight), into `out`: the same rays, bit for bit. A pinhole's are
    /// made eight at once where the CPU has AVX2.
    ///
    /// # Panics
    /// If `pos` holds more than eight positions, or `lens_u` or `out` fewer than `pos`.
    pub fn rays(&self, pos: &[Vec2], lens_u: &[Vec2], out: &mut [Ray]) {
        let n = pos.len();
        assert!(n <= 8 && lens_u.len() >= n && out.len() >= n, "{n} rays");
        #[cfg(target_arch = "x86_64")]
        if n > 1 && std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU runs AVX2 (checked).
            unsafe { self.rays_avx2(pos, lens_u, out) };
            return;
        }
        for j in 0..n {
            out[j] = match &self.lens {
                None => self.ray_pinhole(pos[j]),
                Some(lens) => self.ray_thin_lens(lens, pos[j], lens_u[j]),
            };
        }
    }

    /// [`Camera::rays`] on eight lanes: [`Camera::film_dir`], the lens's point
    /// ([`square_to_uniform_disk_concentric`]) and [`Camera::finish`], the same operations in
    /// the same order (glam's `Mat4::transform_vector3` and `transform_point3` sum the columns
    /// x, y, z (and w) in turn; `Vec3::length` is the root of x x + y y + z z).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn rays_avx2(&self, pos: &[Vec2], lens_u: &[Vec2], out: &mut [Ray]) {
        use _mm256_add_ps as add;
        use _mm256_mul_ps as mul;
        use _mm256_set1_ps as s;
        use _mm256_sub_ps as sub;
        use std::arch::x86_64::*;
        let n = pos.len();
        macro_rules! lane {
            ($v:ident . $c:ident) => {{
                let a: [f32; 8] = std::array::from_fn(|j| $v[j.min(n - 1)].$c);
                _mm256_loadu_ps(a.as_ptr())
            }};
        }
        let (w, h) = self.film_size;
        let neg = s(-0.0);
        let nx = sub(_mm256_div_ps(mul(s(2.0), lane!(pos.x)), s(w as f32)), s(1.0));
        let ny = sub(_mm256_div_ps(mul(s(2.0), lane!(pos.y)), s(h as f32)), s(1.0));
        let film = [
            mul(_mm256_xor_ps(nx, neg), s(self.tan_half.x)),
            mul(_mm256_xor_ps(ny, neg), s(self.tan_half.y)),
            s(1.0),
        ];
        // The ray's origin and direction in camera space.
        let zero = _mm256_setzero_ps();
        let (o, d) = match &self.lens {
            None => ([zero; 3], film),
            Some(lens) => {
                let f = s(lens.focus_distance);
                let focus = [mul(film[0], f), mul(film[1], f), mul(film[2], f)];
                let [dx, dy] = crate::simd::disk_concentric_avx(lane!(lens_u.x), lane!(lens_u.y));
                let ap = s(lens.aperture_radius);
                let (lx, ly) = (mul(dx, ap), mul(dy, ap));
                let o = [lx, ly, zero];
                (o, [sub(focus[0], o[0]), sub(focus[1], o[1]), sub(focus[2], o[2])])
            }
        };
        let m = &self.to_world;
        macro_rules! row {
            ($v:expr, $c:ident) => {
                add(add(mul(s(m.x_axis.$c), $v[0]), mul(s(m.y_axis.$c), $v[1])), mul(s(m.z_axis.$c), $v[2]))
            };
        }
        let (vx, vy, vz) = (row!(d, x), row!(d, y), row!(d, z));
        let len = _mm256_sqrt_ps(add(add(mul(vx, vx), mul(vy, vy)), mul(vz, vz)));
        let per_depth = _mm256_div_ps(len, d[2]);
        let inv = _mm256_div_ps(s(1.0), len);
        let mut l = [[0.0f32; 8]; 8];
        for (k, v) in [
            mul(vx, inv),
            mul(vy, inv),
            mul(vz, inv),
            mul(s(self.near_clip), per_depth),
            mul(s(self.far_clip), per_depth),
            add(s(m.w_axis.x), row!(o, x)),
            add(s(m.w_axis.y), row!(o, y)),
            add(s(m.w_axis.z), row!(o, z)),
        ]
        .into_iter()
        .enumerate()
        {
            _mm256_storeu_ps(l[k].as_mut_ptr(), v);
        }
        for (j, r) in out[..n].iter_mut().enumerate() {
            *r = Ray {
                o: Vec3::new(l[5][j], l[6][j], l[7][j]),
                d: Vec3::new(l[0][j], l[1][j], l[2][j]),
                tmin: l[3][j],
                tmax: l[4][j],
            };
        }
    }

    /// What [`PixelBundles::pixel`] needs of the camera, worked out once.
    pub fn pixel_bundles(&self) -> PixelBundles {
        let m = self.to_world.as_dmat4();
        let t = m.w_axis.truncate();
        let (f, r) = match &self.lens {
            None => (1.0, 0.0),
            Some(l) => (l.focus_distance as f64, l.aperture_radius as f64),
        };
        let r = r + 1e-5 * (t.length() + r);
        // Camera-space planes n . p_c + c to world, relative to the camera: (M^-T n) . (p - t) + c.
        let inv_t = DMat3::from_mat4(m).inverse().transpose();
        PixelBundles {
            size: DVec2::new(self.film_size.0 as f64, self.film_size.1 as f64),
            tan_half: self.tan_half.as_dvec2(),
            axes: [inv_t.x_axis, inv_t.y_axis, inv_t.z_axis],
            origin: self.to_world.transform_point3(Vec3::ZERO).to_array(),
            f,
            r,
            // Lens points lie within r (each axis) of the centre: |M l| <= r (|Mx| + |My|).
            radius: (r * (m.x_axis.truncate().length() + m.y_axis.truncate().length())) as f32,
        }
    }

    /// The world ray from camera-space origin `o` along `d` (not normalised, `d.z > 0`),
    /// clipped to the near and far planes. Normalised once, in world space; `to_world` does not
    /// scale (the loader checks its axes), so the world length stands for the camera-space one
    /// in the clipping distances: depth z lies z |d| / d.z along the unit direction.
    #[inline]
    fn finish(&self, o: Vec3, d: Vec3) -> Ray {
        let v = self.to_world.transform_vector3(d);
        let len = v.length();
        let per_depth = len / d.z;
        Ray {
            o: self.to_world.transform_point3(o),
            d: v * (1.0 / len),
            tmin: self.near_clip * per_depth,
            tmax: self.far_clip * per_depth,
        }
    }
}

/// tan(fov / 2) along x and y for Mitsuba's `fov_axis` values.
pub fn tan_half_fov(fov_deg: f32, axis: &str, width: u32, height: u32) -> Option<Vec2> {
    let aspect = width as f32 / height as f32;
    let t = (fov_deg.to_radians() * 0.5).tan();
    let along_x = |tx: f32| Vec2::new(tx, tx / aspect);
    let along_y = |ty: f32| Vec2::new(ty * aspect, ty);
    Some(match axis {
        "x" => along_x(t),
        "y" => along_y(t),
        "diagonal" => {
            let diag = (width as f32).hypot(height as f32);
            along_x(t * width as f32 / diag)
        }
        "smaller" => {
            if width <= height {
                along_x(t)
            } else {
                along_y(t)
            }
        }
        "larger" => {
            if width >= height {
                along_x(t)
            } else {
                along_y(t)
            }
        }
        _ => return None,
    })
}

/// Scene loading: `perspective` and `thinlens` (`fov`, `fov_axis`, `near_clip`, `far_clip`,
/// `to_world` without scaling; thinlens: `aperture_radius`, `focus_distance`), for a film of
/// `film`'s size.
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
    film: &crate::scene::FilmSettings,
) -> crate::scene::build::R<Camera> {
    let doc = b.doc;
    let to_world = doc.transform(i, "to_world")?.unwrap_or(Mat4::IDENTITY);
    for (k, axis) in [to_world.x_axis, to_world.y_axis, to_world.z_axis].iter().enumerate() {
        if (axis.truncate().length() - 1.0).abs() > 1e-3 {
            return Err(b.err(
                doc.pos_of(i, "to_world"),
                format!(
                    "the sensor's to_world must not scale (axis {k} has length {})",
                    axis.truncate().length()
                ),
            ));
        }
    }
    let fov = doc
        .float(i, "fov")?
        .ok_or_else(|| b.err(doc.obj(i).pos, format!("{} needs a 'fov' (degrees)", doc.describe(i))))?;
    if !(fov > 0.0 && fov < 180.0) {
        return Err(b.err(doc.pos_of(i, "fov"), format!("'fov' must lie in (0, 180) degrees, found {fov}")));
    }
    let axis = doc.string(i, "fov_axis")?.unwrap_or_else(|| "x".into());
    let tan_half = tan_half_fov(fov, &axis, film.width, film.height).ok_or_else(|| {
        b.err(
            doc.pos_of(i, "fov_axis"),
            format!("unknown fov_axis '{axis}' (expected x, y, diagonal, smaller or larger)"),
        )
    })?;
    let near_clip = b.nonneg_float(i, "near_clip", 0.01)?;
    if near_clip == 0.0 {
        return Err(b.err(doc.pos_of(i, "near_clip"), "'near_clip' must be greater than zero"));
    }
    let far_clip = doc.float_or(i, "far_clip", 10000.0)?;
    if !(far_clip > near_clip) {
        return Err(b.err(doc.pos_of(i, "far_clip"), "far_clip must exceed near_clip"));
    }
    let lens = if doc.obj(i).plugin == "thinlens" {
        let aperture_radius = doc
            .float(i, "aperture_radius")?
            .ok_or_else(|| b.err(doc.obj(i).pos, "thinlens needs 'aperture_radius' (world units)"))?;
        if !(aperture_radius >= 0.0) {
            return Err(b.err(doc.pos_of(i, "aperture_radius"), "'aperture_radius' must be >= 0"));
        }
        let focus_distance = doc.float_or(i, "focus_distance", far_clip)?;
        if !(focus_distance > 0.0) {
            return Err(b.err(doc.pos_of(i, "focus_distance"), "'focus_distance' must be > 0"));
        }
        // An aperture of 0 is a pinhole, rendered as one (no lens samples).
        (aperture_radius > 0.0).then_some(ThinLens { aperture_radius, focus_distance })
    } else {
        None
    };
    Ok(Camera { to_world, film_size: (film.width, film.height), tan_half, near_clip, far_clip, lens })
}

/// The bundles of a camera's pixels ([`Camera::pixel_bundles`]).
#[derive(Clone, Debug)]
pub struct PixelBundles {
    size: DVec2,
    tan_half: DVec2,
    /// M^-T's columns (M: the camera's rotation), taking camera-space normals to world.
    axes: [DVec3; 3],
    /// The camera's position, as its rays have it.
    origin: [f32; 3],
    /// Focus distance (1 for a pinhole) and lens radius, grown by the margin.
    f: f64,
    r: f64,
    radius: f32,
}

impl PixelBundles {
    /// The bundle that holds every camera ray of film pixel (`x`, `y`) of the full film
    /// (film positions `[x, x + 1) x [y, y + 1)`, any lens sample), with a margin for the
    /// rays' rounding: 1/64 of a pixel and 1e-5 (1 + s^2) in direction (s: the rays' slope),
    /// and 1e-5 of the camera's distance from the world origin in the lens radius.
    // (Always inlined: release builds' inliner dropped it from `render_region` when unrelated
    // code grew, +3% instructions on textured; docs/BENCHMARKS.md, "Issue 15, twenty-eighth
    // step".)
    #[inline(always)]
    pub fn pixel(&self, x: u32, y: u32) -> Bundle {
        // Camera-space direction (z = 1) ranges of the pixel, grown by the margin.
        // The margin grows with the rays' slope s against the view axis: a ray's f32 rounding
        // is relative to its length, about (1 + s) times its depth, and a lens far wider than
        // its focus distance makes s large however narrow the field of view.
        let range = |p: f64, n: f64, tan: f64| {
            let (a, b) = (-(2.0 * p / n - 1.0) * tan, -(2.0 * (p + 1.0) / n - 1.0) * tan);
            let slope = a.abs().max(b.abs()) + self.r / self.f;
            let m = 2.0 * tan / n / 64.0 + 1e-5 * (1.0 + slope * slope);
            (a.min(b) - m, a.max(b) + m)
        };
        let (dx0, dx1) = range(x as f64, self.size.x, self.tan_half.x);
        let (dy0, dy1) = range(y as f64, self.size.y, self.tan_half.y);
        let (f, r, [ax, ay, az]) = (self.f, self.r, self.axes);
        // A camera-space plane a . axis + k z + c >= 0, in world space relative to the camera.
        let world = |a: DVec3, k: f64, c: f64| ((a + az * k).as_vec3().to_array(), c as f32);
        // At depth z the rays' x spans dx0 z - r |1 - z/f| to dx1 z + r |1 - z/f| (lens
        // points within r of the axis, focused at depth f): a side's bound is one plane
        // before the focus and another past it, and every ray lies inside one of the two.
        let (xl, xh) = ((ax, dx0), (-ax, -dx1));
        let (yl, yh) = ((ay, dy0), (-ay, -dy1));
        let mut planes = [([0.0; 3], 0.0); 9];
        for (s, (a, d)) in [xl, xh, yl, yh].into_iter().enumerate() {
            planes[2 * s] = world(a, -(d + r / f), r);
            planes[2 * s + 1] = world(a, -(d - r / f), -r);
        }
        planes[8] = world(DVec3::ZERO, 1.0, 0.0);
        Bundle { planes, origin: self.origin, radius: self.radius }
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use glam::{DVec3, Vec2, Vec3};

    use crate::geometry::bvh::{Candidates, PACKET};
    use crate::scene::Scene;
    use crate::testing::Pcg;

    const ONE_BELOW: f32 = 1.0 - f32::EPSILON / 2.0;

    /// Film and lens samples of a pixel: the pixel's corners and the lens square's (the
    /// aperture's rim), then random ones.
    fn samples(rng: &mut Pcg, k: usize) -> (Vec2, Vec2) {
        let corner = |c: usize| Vec2::new([0.0, ONE_BELOW][c & 1], [0.0, ONE_BELOW][c >> 1 & 1]);
        // The lens square's edge midpoints: the aperture's rim on its axes.
        let rim =
            [Vec2::new(0.5, 0.0), Vec2::new(0.5, ONE_BELOW), Vec2::new(0.0, 0.5), Vec2::new(ONE_BELOW, 0.5)];
        if k < 8 {
            (corner(k), corner(k / 2 + 1))
        } else if k < 16 {
            (corner(k), rim[k % 4])
        } else {
            (rng.next_2d(), rng.next_2d())
        }
    }

    /// For every `step`-th pixel: every camera ray render_region would trace (pixel corners,
    /// aperture rim, random) lies in the pixel's bundle, and the gathered leaves find the hit
    /// the whole tree finds, at the same distance. Returns the pixels whose gathering was
    /// complete, and the rays that hit something.
    fn check(scene: &Scene, step: u32, rays: usize) -> (usize, usize) {
        let (cam, film) = (&scene.camera, &scene.film);
        let bundles = cam.pixel_bundles();
        let mut cands = Candidates::default();
        let mut rng = Pcg::new(7);
        let (mut complete, mut hits) = (0, 0);
        for y in (0..film.crop_height).step_by(step as usize) {
            for x in (0..film.crop_width).step_by(step as usize) {
                let (px, py) = (x + film.crop_x, y + film.crop_y);
                let bundle = bundles.pixel(px, py);
                scene.accel.gather(&bundle, &mut cands);
                complete += cands.len().is_some() as usize;
                let mut traced = Vec::with_capacity(rays);
                for k in 0..rays {
                    let (f, lens_u) = samples(&mut rng, k);
                    let pos = Vec2::new(px as f32 + f.x, py as f32 + f.y);
                    let ray = match &cam.lens {
                        None => cam.ray_pinhole(pos),
                        Some(lens) => cam.ray_thin_lens(lens, pos, lens_u),
                    };
                    let o = DVec3::from_array(bundle.origin.map(f64::from));
                    assert!((ray.o.as_dvec3() - o).length() <= bundle.radius as f64, "origin outside");
                    for t in [ray.tmin, 0.1, 1.0, 10.0, 100.0, 1e4] {
                        // The ray's points in f64, exactly as its f32 origin and direction define them.
                        let p = ray.o.as_dvec3() + ray.d.as_dvec3() * t.max(ray.tmin) as f64 - o;
                        let inside = |(n, c): ([f32; 3], f32)| {
                            DVec3::from_array(n.map(f64::from)).dot(p) + c as f64 >= 0.0
                        };
                        assert!(
                            inside(bundle.planes[8]),
                            "pixel ({px}, {py}) sample {k}: behind the near plane"
                        );
                        for s in 0..4 {
                            assert!(
                                inside(bundle.planes[2 * s]) || inside(bundle.planes[2 * s + 1]),
                                "pixel ({px}, {py}) sample {k} at t = {t}: outside side {s}"
                            );
                        }
                    }
                    traced.push(ray);
                    let whole = scene.intersect(&ray);
                    let among = scene.intersect_among(&ray, &cands);
                    match (&whole, &among) {
                        (None, None) => {}
                        (Some(a), Some(b)) => {
                            assert_eq!(a.t, b.t, "pixel ({px}, {py}) sample {k}: {ray:?}");
                            hits += 1;
                        }
                        _ => panic!("pixel ({px}, {py}) sample {k}: {ray:?}: {whole:?} against {among:?}"),
                    }
                }
                // In packets, as render_region traces them: each ray's own hit, bit for bit.
                for packet in traced.chunks(PACKET) {
                    let mut out = [None; PACKET];
                    scene.intersect_among_packet(packet, &cands, &mut out[..packet.len()]);
                    for (ray, hit) in packet.iter().zip(out) {
                        let key = |it: Option<crate::geometry::Interaction>| {
                            it.map(|it| {
                                (it.t.to_bits(), it.shape, it.prim, it.p.to_array().map(f32::to_bits))
                            })
                        };
                        let packed = hit.map(|h| scene.accel.hit_interaction(&scene.shapes, ray, &h));
                        assert_eq!(
                            key(packed),
                            key(scene.intersect_among(ray, &cands)),
                            "pixel ({px}, {py}): {ray:?}"
                        );
                    }
                }
            }
        }
        (complete, hits)
    }

    /// `Camera::rays` (a pinhole's eight at once on AVX2) makes the rays `ray_pinhole` and
    /// `ray_thin_lens` make, bit for bit: film corners and edges, points off the film, random
    /// points, one to eight at a time, on the test scenes' cameras.
    #[test]
    fn rays_at_once_are_the_rays_one_at_a_time() {
        for name in ["tests/scenes/cbox.xml", "tests/scenes/envmap.xml", "tests/scenes/thinlens.xml"] {
            let cam = shipped(name).camera;
            let (w, h) = (cam.film_size.0 as f32, cam.film_size.1 as f32);
            let mut rng = Pcg::new(3);
            let mut pos = vec![
                Vec2::ZERO,
                Vec2::new(w, h),
                Vec2::new(w / 2.0, h / 2.0),
                Vec2::new(-3.0, h + 7.0),
                Vec2::new(0.25, ONE_BELOW),
                Vec2::new(w - 0.0001, 0.5),
            ];
            pos.extend((0..3000).map(|_| Vec2::new(rng.next_f32() * w, rng.next_f32() * h)));
            let lens_u: Vec<Vec2> = (0..pos.len()).map(|_| rng.next_2d()).collect();
            let (mut at, mut size) = (0, 0);
            while at < pos.len() {
                size = size % 8 + 1;
                let end = (at + size).min(pos.len());
                let mut out = [crate::geometry::Ray::new(Vec3::ZERO, Vec3::Z); 8];
                cam.rays(&pos[at..end], &lens_u[at..end], &mut out[..end - at]);
                for (j, got) in out[..end - at].iter().enumerate() {
                    let want = match &cam.lens {
                        None => cam.ray_pinhole(pos[at + j]),
                        Some(lens) => cam.ray_thin_lens(lens, pos[at + j], lens_u[at + j]),
                    };
                    let bits = |r: &crate::geometry::Ray| {
                        (
                            r.o.to_array().map(f32::to_bits),
                            r.d.to_array().map(f32::to_bits),
                            r.tmin.to_bits(),
                            r.tmax.to_bits(),
                        )
                    };
                    assert_eq!(bits(got), bits(&want), "{name}: {:?}", pos[at + j]);
                }
                at = end;
            }
        }
    }

    fn shipped(name: &str) -> Scene {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(name);
        Scene::load(&path, &[]).unwrap_or_else(|e| panic!("{name}: {e}"))
    }

    #[test]
    fn gathered_leaves_find_what_the_tree_finds_on_the_test_scenes() {
        for (name, step) in [
            ("tests/scenes/cbox.xml", 5),
            ("tests/scenes/thinlens.xml", 5),
            ("tests/scenes/instances.xml", 5),
            ("tests/scenes/envmap.xml", 5),
            ("tests/scenes/hair.xml", 9),
        ] {
            let mut scene = shipped(name);
            // Every kernel gathers the same leaves at the same distances.
            let gathered = |scene: &Scene| {
                let bundles = scene.camera.pixel_bundles();
                let mut all = Vec::new();
                for y in (0..scene.film.crop_height).step_by(step as usize) {
                    for x in (0..scene.film.crop_width).step_by(step as usize) {
                        let mut c = Candidates::default();
                        scene
                            .accel
                            .gather(&bundles.pixel(x + scene.film.crop_x, y + scene.film.crop_y), &mut c);
                        all.push(c);
                    }
                }
                all
            };
            let reference = gathered(&scene);
            for kernel in crate::geometry::bvh::Kernel::available() {
                scene.accel.set_kernel(kernel);
                assert!(gathered(&scene) == reference, "{name}: {kernel:?} gathers other leaves");
            }
            let (w, h) = (scene.film.crop_width.div_ceil(step), scene.film.crop_height.div_ceil(step));
            // On every kernel (packets of camera rays are traced together on AVX2 only).
            for kernel in crate::geometry::bvh::Kernel::available() {
                scene.accel.set_kernel(kernel);
                let (complete, hits) = check(&scene, step, 12);
                // The fast path is taken on many pixels (in fur, where few leaves suffice), and
                // rays do hit things.
                assert!(complete as u32 * 4 > w * h, "{name}: {complete} of {} pixels complete", w * h);
                assert!(hits > 0, "{name}");
            }
        }
    }

    /// Far from the world's origin (f32 spacing 1e-3 there), a 2-degree lens and a 170-degree
    /// pinhole, both looking at spheres and a panel.
    #[test]
    fn gathered_leaves_hold_far_from_the_origin_and_at_extreme_fields_of_view() {
        let scene = |sensor: &str, fov: f32| {
            let lens = if sensor == "thinlens" {
                r#"<float name="aperture_radius" value="0.3"/><float name="focus_distance" value="40"/>"#
            } else {
                ""
            };
            format!(
                r#"<scene version="3.0.0">
                <integrator type="path"/>
                <sensor type="{sensor}">
                    <float name="fov" value="{fov}"/>
                    {lens}
                    <transform name="to_world">
                        <lookat origin="10000, 5000, -3000" target="10000.3, 5000, -3050" up="0, 1, 0"/>
                    </transform>
                    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="32"/></film>
                </sensor>
                <shape type="sphere"><point name="center" x="10000" y="5000" z="-3040"/><float name="radius" value="0.4"/></shape>
                <shape type="sphere"><point name="center" x="10000.6" y="5000.1" z="-3060"/><float name="radius" value="0.5"/></shape>
                <shape type="sphere"><point name="center" x="10000" y="5000" z="-3000.5"/><float name="radius" value="0.2"/></shape>
                <shape type="rectangle">
                    <transform name="to_world"><scale value="3"/><translate x="10000" y="5000" z="-3080"/></transform>
                </shape>
                <shape type="rectangle">
                    <transform name="to_world"><scale value="0.5"/><rotate y="1" angle="80"/><translate x="10001" y="5000" z="-3002"/></transform>
                </shape>
            </scene>"#
            )
        };
        for (sensor, fov) in
            [("thinlens", 2.0), ("perspective", 2.0), ("perspective", 170.0), ("thinlens", 150.0)]
        {
            let s = Scene::load_str(&scene(sensor, fov), Path::new("far.xml"), &[])
                .unwrap_or_else(|e| panic!("{e}"));
            let (complete, hits) = check(&s, 1, 24);
            assert!(complete > 0 && hits > 0, "{sensor} {fov}: {complete} complete, {hits} hits");
        }
    }

    /// A lens 10,000 times wider than its focus distance: its rays run nearly across the view
    /// axis, and the bundle's margin must follow their slope.
    #[test]
    fn gathered_leaves_hold_for_a_lens_far_wider_than_its_focus_distance() {
        for focus in ["1e-4", "1e-3", "1e-5"] {
            let xml = format!(
                r#"<scene version="3.0.0">
                <integrator type="path"/>
                <sensor type="thinlens">
                    <float name="fov" value="40"/>
                    <float name="aperture_radius" value="1"/>
                    <float name="focus_distance" value="{focus}"/>
                    <transform name="to_world"><lookat origin="0, 0, 0" target="1, 0.7, 0.4" up="0.3, 1, 0.2"/></transform>
                    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
                </sensor>
                <shape type="sphere"><point name="center" x="3" y="2" z="1"/><float name="radius" value="1"/></shape>
                <shape type="sphere"><point name="center" x="-40" y="60" z="-7"/><float name="radius" value="20"/></shape>
                <shape type="sphere"><point name="center" x="500" y="-800" z="90"/><float name="radius" value="200"/></shape>
            </scene>"#
            );
            let s = Scene::load_str(&xml, Path::new("steep.xml"), &[]).unwrap_or_else(|e| panic!("{e}"));
            let (_, hits) = check(&s, 1, 24);
            assert!(hits > 0, "focus {focus}");
        }
    }
}
