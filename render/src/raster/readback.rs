//! Reading targets back to the CPU: copies into mappable buffers (rows padded to 256 bytes),
//! one submit and one wait for all of them, then decoding the targets' bit layouts (`f32`
//! bits in `Rgba32Uint`, four `f16` or two `f32` in `Rg32Uint`).

use glam::{Vec3, Vec4};

use super::{Raster, RasterError};

/// How a target's texels are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Layout {
    /// Four `f32` as bits (16 bytes per pixel).
    Exact4,
    /// Four `f16` in two `u32` (8 bytes per pixel).
    Half4,
    /// Two `f32` as bits (8 bytes per pixel), read into x and y.
    Exact2,
}

impl Layout {
    fn bytes_per_px(self) -> u32 {
        match self {
            Layout::Exact4 => 16,
            Layout::Half4 | Layout::Exact2 => 8,
        }
    }
}

/// Copies `textures` (each `width × height`) to the CPU: submits `enc` with the copies and
/// waits. Returns one plane per texture, in order.
pub(crate) fn read_planes(
    raster: &Raster,
    mut enc: wgpu::CommandEncoder,
    textures: &[(&wgpu::Texture, Layout)],
    width: u32,
    height: u32,
) -> Result<Vec<Vec<Vec4>>, RasterError> {
    let d = &raster.device;
    let size = wgpu::Extent3d {
        width,
        height,
        depth_or_array_layers: 1,
    };
    let mut staged = Vec::new();
    for &(t, layout) in textures {
        let row = (width * layout.bytes_per_px()).div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT)
            * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buf = d.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: row as u64 * height as u64,
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        enc.copy_texture_to_buffer(
            t.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &buf,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(row),
                    rows_per_image: Some(height),
                },
            },
            size,
        );
        staged.push((buf, row, layout));
    }
    raster.queue.submit([enc.finish()]);
    for (buf, _, _) in &staged {
        buf.slice(..).map_async(wgpu::MapMode::Read, |_| {});
    }
    d.poll(wgpu::PollType::Wait {
        submission_index: None,
        timeout: None,
    })
    .map_err(|e| RasterError::Readback(e.to_string()))?;
    let mut planes = Vec::with_capacity(staged.len());
    for (buf, row, layout) in &staged {
        let data = buf
            .slice(..)
            .get_mapped_range()
            .map_err(|e| RasterError::Readback(e.to_string()))?;
        let mut px = Vec::with_capacity((width * height) as usize);
        for y in 0..height as usize {
            let r = &data[y * *row as usize..][..(width * layout.bytes_per_px()) as usize];
            match layout {
                Layout::Exact4 => px.extend(r.chunks_exact(16).map(|c| {
                    let f = |i: usize| {
                        f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]])
                    };
                    Vec4::new(f(0), f(1), f(2), f(3))
                })),
                Layout::Exact2 => px.extend(r.chunks_exact(8).map(|c| {
                    let f = |i: usize| {
                        f32::from_le_bytes([c[4 * i], c[4 * i + 1], c[4 * i + 2], c[4 * i + 3]])
                    };
                    Vec4::new(f(0), f(1), 0.0, 0.0)
                })),
                Layout::Half4 => px.extend(r.chunks_exact(8).map(|c| {
                    let h = |i: usize| half::f16::from_le_bytes([c[2 * i], c[2 * i + 1]]).to_f32();
                    Vec4::new(h(0), h(1), h(2), h(3))
                })),
            }
        }
        drop(data);
        buf.unmap();
        planes.push(px);
    }
    Ok(planes)
}

/// The rgb of a plane.
pub(crate) fn rgb(plane: &[Vec4]) -> Vec<Vec3> {
    plane.iter().map(|v| v.truncate()).collect()
}
