//! A still view's accumulation: while nothing a frame shows changes, each frame samples its
//! pixels at another point within them ([`super::pixel_jitter`]) and is blended into the
//! running mean of the frames so far, so the picture converges to each pixel's mean over its
//! area — what a camera sees and the path tracer's reference shows — instead of the light
//! at its centre. Each frame's pixel is clamped, per channel, to the range of the mean so far
//! over the pixel and its four neighbours (as temporal anti-aliasing clamps): a sub-pixel glimpse of
//! something no neighbour shows (a crack into a lamp's lit housing, which the dungeon's
//! outside view shows at 2,000 times its mean luminance in one frame of sixteen) cannot stand
//! for a share of a pixel. The means' w holds the share of frames that saw a surface.

use wgpu::util::DeviceExt;

use super::Raster;
use super::targets::{Target, overwrite_pass};

/// One image's running mean: two targets (the mean so far and the next one) and the bind
/// group that reads each.
struct Running {
    means: [Target; 2],
    /// `reads[s]`: the fresh image and `means[s]`.
    reads: [wgpu::BindGroup; 2],
}

/// The running means of some of a frame's images (f32-bit targets of one size).
pub(crate) struct Accumulation {
    params: wgpu::Buffer,
    images: Vec<Running>,
    /// Which of each image's `means` holds the newest mean.
    current: usize,
}

impl Accumulation {
    /// Running means of `fresh` (each frame's images; their w, 1 where a surface was drawn
    /// and 0 elsewhere, becomes the share of frames that saw one).
    pub(crate) fn new(raster: &Raster, fresh: &[&Target], (width, height): (u32, u32)) -> Self {
        let params = raster
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("accumulation"),
                contents: &[0u8; 16],
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            });
        let format = raster.formats().exact4;
        let images = fresh
            .iter()
            .map(|image| {
                let means = [0, 1].map(|_| Target::new(raster, "mean", width, height, format));
                let reads = [0, 1].map(|s| {
                    fn texture(binding: u32, t: &Target) -> wgpu::BindGroupEntry<'_> {
                        wgpu::BindGroupEntry {
                            binding,
                            resource: wgpu::BindingResource::TextureView(&t.view),
                        }
                    }
                    raster.device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some("accumulation"),
                        layout: &raster.pipelines.accumulate_layout,
                        entries: &[
                            texture(0, image),
                            texture(1, &means[s]),
                            wgpu::BindGroupEntry {
                                binding: 2,
                                resource: params.as_entire_binding(),
                            },
                        ],
                    })
                });
                Running { means, reads }
            })
            .collect();
        Accumulation {
            params,
            images,
            current: 0,
        }
    }

    /// Records frame `frame` of the still view (0 starts the mean again) into every mean.
    pub(crate) fn encode(&mut self, raster: &Raster, enc: &mut wgpu::CommandEncoder, frame: u32) {
        let params = [frame, 0, 0, 0];
        raster
            .queue
            .write_buffer(&self.params, 0, bytemuck::cast_slice(&params));
        let next = 1 - self.current;
        for image in &self.images {
            let mut pass = overwrite_pass(enc, "accumulate", &image.means[next].view);
            pass.set_pipeline(&raster.pipelines.accumulate);
            pass.set_bind_group(0, &image.reads[self.current], &[]);
            pass.draw(0..3, 0..1);
        }
        self.current = next;
    }

    /// The newest mean of image `i` (in the order given to [`Accumulation::new`]), if it is
    /// accumulated.
    pub(crate) fn mean(&self, i: usize) -> Option<&Target> {
        self.images.get(i).map(|image| &image.means[self.current])
    }
}
