"""Writes tests/scenes/assets/sun_sky.exr: a 1024 x 512 lat-long map (Mitsuba's convention:
u = atan2(d.x, -d.z) / 2pi, v = acos(d.y) / pi, row 0 = +y) with a sun 0.5 degrees across of
radiance 1e5 (warm white), a sky from a blue zenith to a pale horizon, and a dark ground.
Every texel is the mean of 8 x 8 points (the sun's edge is antialiased).

    bench/peers/py.sh bench/peers/make_sun_map.py [OUT.exr]
"""
import sys

import numpy as np
import mitsuba as mi

mi.set_variant("scalar_rgb")

W, H, SS = 1024, 512, 8
SUN_ELEVATION, SUN_AZIMUTH = np.radians(30.0), np.radians(40.0)  # azimuth from +z towards +x
SUN_RADIUS = np.radians(0.25)
SUN = np.array([1.0e5, 0.96e5, 0.88e5])
ZENITH, HORIZON, GROUND = np.array([0.10, 0.18, 0.40]), np.array([0.45, 0.50, 0.55]), np.array([0.08, 0.07, 0.06])

sun_dir = np.array([np.cos(SUN_ELEVATION) * np.sin(SUN_AZIMUTH), np.sin(SUN_ELEVATION),
                    np.cos(SUN_ELEVATION) * np.cos(SUN_AZIMUTH)])
out = np.zeros((H, W, 3))
s = (np.arange(SS) + 0.5) / SS
for j in range(H):
    v = (j + s[:, None]) / H                       # SS x 1
    u = (np.arange(W)[:, None, None] + s[None, None, :]) / W   # W x 1 x SS
    theta, phi = np.pi * v[None, :, :], 2 * np.pi * u         # W x SS x SS (broadcast)
    d = np.stack(np.broadcast_arrays(np.sin(theta) * np.sin(phi), np.cos(theta) + 0 * phi,
                                     -np.sin(theta) * np.cos(phi)), axis=-1)
    up = d[..., 1:2]
    t = np.clip(up, 0.0, 1.0) ** 0.5
    sky = np.where(up > 0, HORIZON * (1 - t) + ZENITH * t, GROUND)
    in_sun = (d @ sun_dir) >= np.cos(SUN_RADIUS)
    sky = np.where(in_sun[..., None], SUN, sky)
    out[j] = sky.mean(axis=(1, 2))
path = sys.argv[1] if len(sys.argv) > 1 else "tests/scenes/assets/sun_sky.exr"
mi.Bitmap(out.astype(np.float32)).write(path)
print(f"{path}: {W}x{H}, sun {np.degrees(2 * SUN_RADIUS):.2f} deg across towards {np.round(sun_dir, 4)}")
