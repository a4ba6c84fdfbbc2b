//! Writing float images: OpenEXR for the numbers, tone-mapped PNG for the eyes.

use std::path::Path;

use glam::Vec3;

use crate::metrics::tonemap;

/// Why an image could not be written.
#[derive(Debug, thiserror::Error)]
#[error("cannot write {path}: {source}")]
pub struct ImageError {
    path: String,
    source: image::ImageError,
}

/// Writes linear RGB radiance as a 32-bit float OpenEXR file.
pub fn write_exr(path: &Path, width: u32, height: u32, pixels: &[Vec3]) -> Result<(), ImageError> {
    let data: Vec<f32> = pixels.iter().flat_map(|v| [v.x, v.y, v.z]).collect();
    let img =
        image::Rgb32FImage::from_raw(width, height, data).expect("pixel count matches the size");
    img.save(path).map_err(|source| ImageError {
        path: path.display().to_string(),
        source,
    })
}

/// Reads an OpenEXR (or any float) image as linear RGB.
pub fn read_exr(path: &Path) -> Result<(u32, u32, Vec<Vec3>), ImageError> {
    let img = image::open(path)
        .map_err(|source| ImageError {
            path: path.display().to_string(),
            source,
        })?
        .to_rgb32f();
    let (w, h) = img.dimensions();
    Ok((
        w,
        h,
        img.pixels().map(|p| Vec3::new(p[0], p[1], p[2])).collect(),
    ))
}

/// Writes an sRGB PNG of the image tone-mapped with ACES at exposure `2^stops`.
pub fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    pixels: &[Vec3],
    stops: f32,
) -> Result<(), ImageError> {
    let img = image::RgbImage::from_raw(width, height, tonemap(pixels, stops))
        .expect("pixel count matches the size");
    img.save(path).map_err(|source| ImageError {
        path: path.display().to_string(),
        source,
    })
}

/// An exposure (stops) that maps the image's 99th-percentile luminance to about 0.8.
pub fn auto_exposure(pixels: &[Vec3]) -> f32 {
    let mut y: Vec<f32> = pixels
        .iter()
        .map(|v| v.dot(Vec3::new(0.2126, 0.7152, 0.0722)))
        .filter(|y| *y > 0.0 && y.is_finite())
        .collect();
    if y.is_empty() {
        return 0.0;
    }
    y.sort_by(f32::total_cmp);
    let p99 = y[(y.len() * 99 / 100).min(y.len() - 1)];
    (0.8 / p99).log2()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exr_round_trips_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.exr");
        let px: Vec<Vec3> = (0..12)
            .map(|i| Vec3::new(i as f32 * 0.5, 1e-6, 1e6))
            .collect();
        write_exr(&p, 4, 3, &px).unwrap();
        let (w, h, back) = read_exr(&p).unwrap();
        assert_eq!((w, h), (4, 3));
        assert_eq!(back, px);
        write_png(&dir.path().join("x.png"), 4, 3, &px, auto_exposure(&px)).unwrap();
        assert!(write_exr(Path::new("/nonexistent/dir/x.exr"), 4, 3, &px).is_err());
    }
}
