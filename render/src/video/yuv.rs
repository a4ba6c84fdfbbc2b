//! 8-bit 4:2:0 planes (I420) and the RGB8 ↔ YUV conversion of SDR frames.
//!
//! Matrix and range: **BT.709, full range** (Y, Cb, Cr all use 0–255; Cb and Cr are centred
//! on 128), signalled in the stream's VUI so that other decoders (ffmpeg) convert back the
//! same way. RGB8 is taken as sRGB-encoded (what the raster's read-back gives), so the
//! transfer characteristic signalled is IEC 61966-2-1. Chroma is the average of each 2×2
//! block's Cb/Cr (co-sited between the four luma samples, MPEG-2 style: ffmpeg's default).

/// Kr and Kb of BT.709.
const KR: f32 = 0.2126;
const KB: f32 = 0.0722;
const KG: f32 = 1.0 - KR - KB;

/// Largest frame side openh264 encodes (level 5.2: 3840×2160 either way round).
pub const MAX_SIDE: u32 = 3840;

/// Why a frame cannot be made or converted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// Width or height is zero, odd, or beyond what H.264 level 5.2 holds.
    #[error(
        "a {width}×{height} frame cannot be encoded: sides must be even, at least 2, at most {MAX_SIDE}×2160 (either way round)"
    )]
    Size {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// The pixel buffer does not hold width × height pixels.
    #[error("{got} bytes given for a {width}×{height} frame of {want} bytes")]
    Length {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
        /// Bytes given.
        got: usize,
        /// Bytes needed.
        want: usize,
    },
}

/// Checks a frame size against what the encoder takes.
pub fn check_size(width: u32, height: u32) -> Result<(), FrameError> {
    let (long, short) = (width.max(height), width.min(height));
    if width < 2
        || height < 2
        || width % 2 == 1
        || height % 2 == 1
        || long > MAX_SIDE
        || short > 2160
    {
        return Err(FrameError::Size { width, height });
    }
    Ok(())
}

/// An I420 frame: a full-resolution Y plane and half-resolution U and V planes, tightly
/// packed (strides = widths).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Yuv420 {
    /// Width, pixels (even).
    pub width: u32,
    /// Height, pixels (even).
    pub height: u32,
    /// Luma, `width × height`.
    pub y: Vec<u8>,
    /// Cb, `width/2 × height/2`.
    pub u: Vec<u8>,
    /// Cr, `width/2 × height/2`.
    pub v: Vec<u8>,
}

impl Yuv420 {
    /// A frame of one colour.
    pub fn filled(width: u32, height: u32, yuv: [u8; 3]) -> Result<Self, FrameError> {
        check_size(width, height)?;
        let (n, c) = ((width * height) as usize, (width * height / 4) as usize);
        Ok(Yuv420 {
            width,
            height,
            y: vec![yuv[0]; n],
            u: vec![yuv[1]; c],
            v: vec![yuv[2]; c],
        })
    }

    /// Chroma plane width (and stride).
    pub fn chroma_width(&self) -> u32 {
        self.width / 2
    }

    /// Converts RGB8 (row-major from the top, 3 bytes per pixel) to BT.709 full-range I420.
    pub fn from_rgb8(width: u32, height: u32, rgb: &[u8]) -> Result<Self, FrameError> {
        check_size(width, height)?;
        let want = width as usize * height as usize * 3;
        if rgb.len() != want {
            return Err(FrameError::Length {
                width,
                height,
                got: rgb.len(),
                want,
            });
        }
        let (w, h) = (width as usize, height as usize);
        let mut out = Yuv420::filled(width, height, [0, 128, 128])?;
        let px = |x: usize, y: usize| {
            let i = (y * w + x) * 3;
            [rgb[i] as f32, rgb[i + 1] as f32, rgb[i + 2] as f32]
        };
        for y in 0..h {
            for x in 0..w {
                let [r, g, b] = px(x, y);
                out.y[y * w + x] = to_u8(KR * r + KG * g + KB * b);
            }
        }
        let cw = w / 2;
        for cy in 0..h / 2 {
            for cx in 0..cw {
                let mut sum = [0.0f32; 3];
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let p = px(2 * cx + dx, 2 * cy + dy);
                    sum = [sum[0] + p[0], sum[1] + p[1], sum[2] + p[2]];
                }
                let [r, g, b] = sum.map(|s| s * 0.25);
                let luma = KR * r + KG * g + KB * b;
                out.u[cy * cw + cx] = to_u8((b - luma) / (2.0 * (1.0 - KB)) + 128.0);
                out.v[cy * cw + cx] = to_u8((r - luma) / (2.0 * (1.0 - KR)) + 128.0);
            }
        }
        Ok(out)
    }

    /// Converts back to RGB8 (the inverse of [`Yuv420::from_rgb8`], chroma upsampled by
    /// nearest neighbour).
    pub fn to_rgb8(&self) -> Vec<u8> {
        let (w, h) = (self.width as usize, self.height as usize);
        let cw = w / 2;
        let mut rgb = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                let luma = self.y[y * w + x] as f32;
                let cb = self.u[(y / 2) * cw + x / 2] as f32 - 128.0;
                let cr = self.v[(y / 2) * cw + x / 2] as f32 - 128.0;
                let r = luma + 2.0 * (1.0 - KR) * cr;
                let b = luma + 2.0 * (1.0 - KB) * cb;
                let g = (luma - KR * r - KB * b) / KG;
                let i = (y * w + x) * 3;
                rgb[i] = to_u8(r);
                rgb[i + 1] = to_u8(g);
                rgb[i + 2] = to_u8(b);
            }
        }
        rgb
    }
}

fn to_u8(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// Peak signal-to-noise ratio of two equal-length 8-bit buffers, dB (infinite when equal).
pub fn psnr(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len(), "PSNR of buffers of different sizes");
    let se: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    if se == 0.0 {
        return f64::INFINITY;
    }
    let mse = se / a.len() as f64;
    10.0 * (255.0 * 255.0 / mse).log10()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_must_be_even_and_within_level_5_2() {
        assert!(check_size(320, 240).is_ok());
        assert!(check_size(2160, 3840).is_ok());
        for (w, h) in [
            (0, 2),
            (3, 2),
            (2, 5),
            (3842, 2),
            (4000, 2160),
            (2200, 2200),
        ] {
            assert!(check_size(w, h).is_err(), "{w}×{h}");
        }
        assert!(matches!(
            Yuv420::from_rgb8(4, 4, &[0; 47]),
            Err(FrameError::Length { want: 48, .. })
        ));
    }

    #[test]
    fn flat_colours_round_trip_within_a_code_value() {
        for rgb in [
            [0, 0, 0],
            [255, 255, 255],
            [255, 0, 0],
            [0, 255, 0],
            [0, 0, 255],
            [90, 140, 200],
        ] {
            let frame: Vec<u8> = std::iter::repeat_n(rgb, 16).flatten().collect();
            let yuv = Yuv420::from_rgb8(4, 4, &frame).unwrap();
            let back = yuv.to_rgb8();
            for (a, b) in frame.iter().zip(&back) {
                assert!(a.abs_diff(*b) <= 2, "{rgb:?} came back as {:?}", &back[..3]);
            }
        }
        // Grey has no chroma.
        let grey = Yuv420::from_rgb8(2, 2, &[77; 12]).unwrap();
        assert_eq!((grey.y[0], grey.u[0], grey.v[0]), (77, 128, 128));
    }

    #[test]
    fn psnr_of_equal_and_of_offset_buffers() {
        assert_eq!(psnr(&[1, 2, 3], &[1, 2, 3]), f64::INFINITY);
        // Every sample off by one: MSE 1 → 20·log10(255) ≈ 48.13 dB.
        let p = psnr(&[10; 100], &[11; 100]);
        assert!((p - 48.13).abs() < 0.01, "{p}");
    }
}
