//! `cloudlight reference SCENE`: the path tracer's full, direct and indirect images.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};

use super::ranges;

/// Options of `reference`.
#[derive(clap::Args)]
pub struct Args {
    /// Scene: `cornell`, `cornell-animated`, `city:N` or a .gltf/.glb file.
    scene: String,
    /// View: the index of one of the scene's camera paths, or `px,py,pz:tx,ty,tz[:fov_deg]`
    /// (eye and target in meters, vertical field of view in degrees, default 45).
    #[arg(long, default_value = "0", allow_hyphen_values = true)]
    camera: String,
    /// Scene time, seconds.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true,
          value_parser = ranges::closed(-ranges::MAX_SECONDS, ranges::MAX_SECONDS, "seconds"))]
    time: f64,
    /// Samples per pixel.
    #[arg(long, default_value_t = 256, value_parser = ranges::count::<u32>(1, ranges::MAX_SPP))]
    spp: u32,
    /// Image width, pixels (width × height at most 4096²).
    #[arg(long, default_value_t = 512, value_parser = ranges::count::<u32>(1, ranges::MAX_IMAGE_SIDE))]
    width: u32,
    /// Image height, pixels.
    #[arg(long, default_value_t = 512, value_parser = ranges::count::<u32>(1, ranges::MAX_IMAGE_SIDE))]
    height: u32,
    /// Seed of the random streams.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Where each camera ray passes in its pixel: `area` (jittered over it, the pixel's
    /// mean: what `bench quality` judges against) or `centre` (its centre only, as a raster
    /// client shades it).
    #[arg(long, value_enum, default_value_t = Pixel::Area)]
    pixel: Pixel,
    /// Output folder for full/direct/indirect .exr and .png.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

/// `--pixel`: [`cloudlight::render::PixelSampling`].
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum Pixel {
    Area,
    Centre,
}

/// Renders `spp` samples per pixel in passes of 4, with a progress bar.
fn render_with_progress(
    renderer: &cloudlight::render::ReferenceRenderer<'_>,
    images: &mut cloudlight::render::ReferenceImages,
    spp: u32,
) {
    let bar = ProgressBar::new(spp as u64).with_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} spp, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let pass = 4.min(spp);
    let mut done = 0;
    while done < spp {
        let n = pass.min(spp - done);
        renderer.render_pass(images, done, n);
        done += n;
        bar.set_position(done as u64);
    }
    bar.finish_and_clear();
}

/// Writes full, direct and indirect as EXR and PNG (one exposure for all three).
fn write_images(
    args: &Args,
    images: &cloudlight::render::ReferenceImages,
) -> Result<(), cloudlight::render::image_io::ImageError> {
    use cloudlight::render::image_io;
    let full = images.full();
    let stops = image_io::auto_exposure(&full);
    for (name, img) in [
        ("full", full.clone()),
        ("direct", images.direct()),
        ("indirect", images.indirect()),
    ] {
        let (w, h) = (args.width, args.height);
        image_io::write_exr(&args.out.join(format!("{name}.exr")), w, h, &img)?;
        image_io::write_png(&args.out.join(format!("{name}.png")), w, h, &img, stops)?;
    }
    Ok(())
}

pub fn run(args: Args) -> ExitCode {
    use cloudlight::render::{
        BvhKind, ReferenceImages, ReferenceRenderer, RenderSettings, SceneBvh,
    };
    // Four f32 images of 4 channels per pixel are held (full, direct, indirect, and the
    // accumulation): 16,384² pixels is about 17 GB, so the product is bounded well below
    // (each side is bounded by its flag's parser).
    const MAX_PIXELS: u64 = 4096 * 4096;
    let pixels = args.width as u64 * args.height as u64;
    if pixels > MAX_PIXELS {
        eprintln!(
            "error: --width {} --height {} is {pixels} pixels, more than {MAX_PIXELS} (4096²)",
            args.width, args.height
        );
        return ExitCode::from(2);
    }
    let scene = match super::load_scene(&args.scene) {
        Ok(s) => s,
        Err(code) => return code,
    };
    let camera = match cloudlight::scenes::camera(&scene, &args.camera, args.time) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("error: --camera: {e}");
            return ExitCode::from(2);
        }
    };
    if let Err(e) = std::fs::create_dir_all(&args.out) {
        eprintln!("error: cannot create {}: {e}", args.out.display());
        return ExitCode::FAILURE;
    }
    let t0 = Instant::now();
    let bvh = SceneBvh::at(&scene, args.time, BvhKind::default());
    let settings = RenderSettings {
        width: args.width,
        height: args.height,
        camera,
        time_s: args.time,
        seed: args.seed,
        max_bounces: 256,
        pixel: match args.pixel {
            Pixel::Area => cloudlight::render::PixelSampling::Area,
            Pixel::Centre => cloudlight::render::PixelSampling::Centre,
        },
    };
    let renderer = ReferenceRenderer::new(&scene, &bvh, settings);
    let mut images = ReferenceImages::new(args.width, args.height);
    let render_start = Instant::now();
    render_with_progress(&renderer, &mut images, args.spp);
    let render_s = render_start.elapsed().as_secs_f64();
    if let Err(e) = write_images(&args, &images) {
        eprintln!("error: {e}");
        return ExitCode::FAILURE;
    }
    println!(
        "{}: {}x{} at {} spp, time {} s: rendered in {:.2} s ({:.2} s with BVH build); wrote full, direct and indirect .exr/.png to {}",
        scene.name,
        args.width,
        args.height,
        args.spp,
        args.time,
        render_s,
        t0.elapsed().as_secs_f64(),
        args.out.display()
    );
    ExitCode::SUCCESS
}
