//! Mitsuba's `perspective` and `thinlens` sensors.
//!
//! Camera space: +z forward, +y up, +x towards the image's left (Mitsuba's `lookat`).
//! Near and far clipping are planes at camera-space z = near / far, as in Mitsuba.
//! The thin lens focuses on the plane z = `focus_distance` and samples the aperture uniformly
//! (concentric map) without a vignetting weight, again as Mitsuba does.

use glam::{Mat4, Vec2, Vec3};

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
