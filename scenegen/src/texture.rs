//! Textures: glTF image textures with sampler wrap modes and nearest / bilinear filtering
//! ([`Texture`]), procedural solid textures for the stage ([`Procedural`]), and the sRGB
//! transfer functions. Colours are linear RGB(A) `Vec4`s everywhere outside the 8-bit images.

use glam::{Vec3, Vec4};

/// sRGB-encoded `[0, 1]` to linear.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Linear to sRGB-encoded `[0, 1]` (input clamped to `[0, 1]`).
pub fn linear_to_srgb(c: f32) -> f32 {
    let c = if c.is_nan() { 0.0 } else { c.clamp(0.0, 1.0) };
    if c <= 0.0031308 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
}

/// A linear colour from 8-bit-style sRGB components in `[0, 1]`.
pub fn srgb(r: f32, g: f32, b: f32) -> Vec3 {
    Vec3::new(srgb_to_linear(r), srgb_to_linear(g), srgb_to_linear(b))
}

/// Texture coordinate wrapping (glTF sampler `wrapS` / `wrapT`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    Repeat,
    ClampToEdge,
    MirroredRepeat,
}

impl Wrap {
    pub fn from_gltf(w: gltf::texture::WrappingMode) -> Self {
        match w {
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
            gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
        }
    }

    /// Texel index for integer texel coordinate `i` in a row of `n` texels.
    pub fn apply(self, i: i64, n: u32) -> u32 {
        let n = n as i64;
        let r = match self {
            Wrap::Repeat => i.rem_euclid(n),
            Wrap::ClampToEdge => i.clamp(0, n - 1),
            Wrap::MirroredRepeat => {
                let p = i.rem_euclid(2 * n);
                if p < n {
                    p
                } else {
                    2 * n - 1 - p
                }
            }
        };
        r as u32
    }
}

/// Texture filtering.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filter {
    Nearest,
    Bilinear,
}

/// A decoded image texture: linear RGBA texels, row 0 at the top (`v = 0`, glTF convention).
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    pub width: u32,
    pub height: u32,
    pub texels: Vec<Vec4>,
    pub wrap_s: Wrap,
    pub wrap_t: Wrap,
    pub filter: Filter,
}

impl Texture {
    /// From an 8-bit sRGB RGBA image (colour decoded to linear, alpha kept linear).
    pub fn from_rgba8(img: &image::RgbaImage, wrap_s: Wrap, wrap_t: Wrap, filter: Filter) -> Self {
        let lut: Vec<f32> = (0..256).map(|v| srgb_to_linear(v as f32 / 255.0)).collect();
        let texels = img
            .pixels()
            .map(|p| {
                Vec4::new(
                    lut[p[0] as usize],
                    lut[p[1] as usize],
                    lut[p[2] as usize],
                    p[3] as f32 / 255.0,
                )
            })
            .collect();
        Texture {
            width: img.width(),
            height: img.height(),
            texels,
            wrap_s,
            wrap_t,
            filter,
        }
    }

    fn texel(&self, x: i64, y: i64) -> Vec4 {
        let x = self.wrap_s.apply(x, self.width);
        let y = self.wrap_t.apply(y, self.height);
        self.texels[(y * self.width + x) as usize]
    }

    /// The colour at texture coordinates `(u, v)` (texel centres at `(i + 0.5) / width`).
    pub fn sample(&self, u: f32, v: f32) -> Vec4 {
        let (u, v) = (
            if u.is_finite() { u } else { 0.0 },
            if v.is_finite() { v } else { 0.0 },
        );
        // Keep coordinates in a range where i64 conversion is exact.
        let x = (u * self.width as f32).clamp(-1e9, 1e9);
        let y = (v * self.height as f32).clamp(-1e9, 1e9);
        match self.filter {
            Filter::Nearest => self.texel(x.floor() as i64, y.floor() as i64),
            Filter::Bilinear => {
                let (xs, ys) = (x - 0.5, y - 0.5);
                let (x0, y0) = (xs.floor(), ys.floor());
                let (fx, fy) = (xs - x0, ys - y0);
                let (x0, y0) = (x0 as i64, y0 as i64);
                let top = self.texel(x0, y0) * (1.0 - fx) + self.texel(x0 + 1, y0) * fx;
                let bottom = self.texel(x0, y0 + 1) * (1.0 - fx) + self.texel(x0 + 1, y0 + 1) * fx;
                top * (1.0 - fy) + bottom * fy
            }
        }
    }
}

// -------------------------------------------------------------------------------------------
// Procedural solid textures (functions of the world position) for the stage.

fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Uniform in `[0, 1)` from a seed and an integer lattice point.
pub fn hash01(seed: u64, a: i64, b: i64, c: i64) -> f32 {
    let mut h = mix64(seed ^ 0x9E37_79B9_7F4A_7C15);
    for v in [a, b, c] {
        h = mix64(h ^ (v as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    }
    (h >> 40) as f32 / (1u64 << 24) as f32
}

fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// 3D value noise in `[0, 1]`, unit lattice.
pub fn value_noise(seed: u64, p: Vec3) -> f32 {
    let f = p.floor();
    let (ix, iy, iz) = (f.x as i64, f.y as i64, f.z as i64);
    let t = p - f;
    let (tx, ty, tz) = (smooth(t.x), smooth(t.y), smooth(t.z));
    let mut acc = 0.0;
    for dz in 0..2 {
        for dy in 0..2 {
            for dx in 0..2 {
                let w = (if dx == 1 { tx } else { 1.0 - tx })
                    * (if dy == 1 { ty } else { 1.0 - ty })
                    * (if dz == 1 { tz } else { 1.0 - tz });
                acc += w * hash01(seed, ix + dx, iy + dy, iz + dz);
            }
        }
    }
    acc
}

/// Two octaves of value noise in `[0, 1]`.
pub fn fbm(seed: u64, p: Vec3) -> f32 {
    (value_noise(seed, p) * 2.0 + value_noise(seed ^ 1, p * 2.03)) / 3.0
}

/// A procedural solid texture.
#[derive(Clone, Debug, PartialEq)]
pub enum Procedural {
    /// 3D checker of cell size `scale`, modulated by noise of relative amplitude `noise`.
    Checker {
        scale: f32,
        a: Vec3,
        b: Vec3,
        noise: f32,
        seed: u64,
    },
    /// Bricks on a plane spanned by world axes `u_axis`, `v_axis` (indices 0..3).
    Brick {
        u_axis: usize,
        v_axis: usize,
        width: f32,
        height: f32,
        brick: Vec3,
        mortar: Vec3,
        seed: u64,
    },
    /// Smooth coloured noise blended between `a` and `b`, plus a third colour in the ridges.
    Marble {
        scale: f32,
        a: Vec3,
        b: Vec3,
        c: Vec3,
        seed: u64,
    },
    /// Voronoi-like cells: each lattice cell gets a random tint of `base`.
    Cells { scale: f32, base: Vec3, seed: u64 },
}

impl Procedural {
    /// Linear albedo at world point `p`.
    pub fn albedo(&self, p: Vec3) -> Vec3 {
        match *self {
            Procedural::Checker {
                scale,
                a,
                b,
                noise,
                seed,
            } => {
                let q = (p / scale).floor();
                let parity = (q.x as i64 + q.y as i64 + q.z as i64).rem_euclid(2);
                let base = if parity == 0 { a } else { b };
                base * (1.0 - noise + 2.0 * noise * fbm(seed, p * 3.0))
            }
            Procedural::Brick {
                u_axis,
                v_axis,
                width,
                height,
                brick,
                mortar,
                seed,
            } => {
                let (u, v) = (p[u_axis], p[v_axis]);
                let row = (v / height).floor();
                let shift = if (row as i64).rem_euclid(2) == 1 {
                    0.5
                } else {
                    0.0
                };
                let col = (u / width + shift).floor();
                let fu = u / width + shift - col;
                let fv = v / height - row;
                let m = 0.06;
                if fu < m * height / width || fv < m {
                    mortar
                } else {
                    let tint = 0.75 + 0.5 * hash01(seed, col as i64, row as i64, 7);
                    brick * tint * (0.85 + 0.3 * value_noise(seed, p * 8.0))
                }
            }
            Procedural::Marble {
                scale,
                a,
                b,
                c,
                seed,
            } => {
                let n = fbm(seed, p / scale);
                let ridge = (1.0 - ((n * 12.0).sin()).abs()).powi(6);
                a.lerp(b, n) * (1.0 - ridge) + c * ridge
            }
            Procedural::Cells { scale, base, seed } => {
                let q = p / scale;
                let f = q.floor();
                let mut best = (f32::INFINITY, 0.0f32, f32::INFINITY);
                for dz in -1..=1 {
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            let c = f + Vec3::new(dx as f32, dy as f32, dz as f32);
                            let (cx, cy, cz) = (c.x as i64, c.y as i64, c.z as i64);
                            let site = c + Vec3::new(
                                hash01(seed, cx, cy, cz),
                                hash01(seed ^ 2, cx, cy, cz),
                                hash01(seed ^ 3, cx, cy, cz),
                            );
                            let d = (q - site).length();
                            if d < best.0 {
                                best = (d, hash01(seed ^ 5, cx, cy, cz), best.0);
                            } else if d < best.2 {
                                best.2 = d;
                            }
                        }
                    }
                }
                let edge = ((best.2 - best.0) * 6.0).clamp(0.0, 1.0);
                let tint = Vec3::new(0.6 + 0.8 * best.1, 1.0, 1.4 - 0.8 * best.1);
                (base * tint * (0.35 + 0.65 * edge)).min(Vec3::ONE)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srgb_round_trip() {
        for i in 0..=255 {
            let c = i as f32 / 255.0;
            assert!((linear_to_srgb(srgb_to_linear(c)) - c).abs() < 1e-5);
        }
    }

    #[test]
    fn wrap_modes() {
        assert_eq!(Wrap::Repeat.apply(-1, 4), 3);
        assert_eq!(Wrap::Repeat.apply(5, 4), 1);
        assert_eq!(Wrap::ClampToEdge.apply(-3, 4), 0);
        assert_eq!(Wrap::ClampToEdge.apply(9, 4), 3);
        // Mirrored: 0 1 2 3 | 3 2 1 0 | 0 1 ...
        let m: Vec<u32> = (-2..10).map(|i| Wrap::MirroredRepeat.apply(i, 4)).collect();
        assert_eq!(m, vec![1, 0, 0, 1, 2, 3, 3, 2, 1, 0, 0, 1]);
    }

    fn two_by_one(filter: Filter, wrap: Wrap) -> Texture {
        let mut img = image::RgbaImage::new(2, 1);
        img.put_pixel(0, 0, image::Rgba([0, 0, 0, 255]));
        img.put_pixel(1, 0, image::Rgba([255, 255, 255, 255]));
        Texture::from_rgba8(&img, wrap, wrap, filter)
    }

    #[test]
    fn nearest_and_bilinear_sampling() {
        let t = two_by_one(Filter::Nearest, Wrap::ClampToEdge);
        assert_eq!(t.sample(0.2, 0.5).x, 0.0);
        assert_eq!(t.sample(0.7, 0.5).x, 1.0);
        let t = two_by_one(Filter::Bilinear, Wrap::ClampToEdge);
        // Texel centres at u = 0.25 and 0.75; halfway between is the mean (linear values).
        assert!((t.sample(0.5, 0.5).x - 0.5).abs() < 1e-6);
        assert_eq!(t.sample(0.1, 0.5).x, 0.0);
        // With REPEAT, u = 0 lies between the last and the first texel.
        let t = two_by_one(Filter::Bilinear, Wrap::Repeat);
        assert!((t.sample(0.0, 0.5).x - 0.5).abs() < 1e-6);
    }
}
