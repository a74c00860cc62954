//! `b2dr render`: one Bench2Drive-R frame of a keyframe (see `b2dr::render::job`).
use std::path::PathBuf;

use anyhow::Result;
use b2dr::render::job::{self, RenderJob};
use b2dr::tensor::DType;
use b2dr::vk::{Context, ContextOptions};

#[derive(clap::Args, Debug)]
pub struct RenderArgs {
    /// Model package folder (b2dr.json, unet/, controlnet/, vae/, context.safetensors); default: the built-in
    /// b2dr-tiny (seeded random weights: an untrained renderer)
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Keyframe JSON (the format of nuscenes-mini/keyframe-scene-0061/frame.json): cameras, poses, boxes
    #[arg(long)]
    pub frame: PathBuf,
    /// Previous frames: one image per camera (camera order), or a folder of <CAMERA>.png (e.g. an earlier
    /// render's output); default: the frame's own recorded images (a run's first frame)
    #[arg(long, num_args = 1..)]
    pub prev: Vec<PathBuf>,
    /// Two keyframe JSONs whose images of each camera are its front and rear references; default: the
    /// frame's own images on both sides
    #[arg(long, num_args = 2)]
    pub refs: Option<Vec<PathBuf>>,
    /// Masks-only rendering (no references: the Ref-Attns are skipped)
    #[arg(long)]
    pub no_refs: bool,
    /// Comma-separated cameras (default: the model's cameras present in the frame)
    #[arg(long, value_delimiter = ',')]
    pub cameras: Option<Vec<String>>,
    /// Sampling steps (default: the model's)
    #[arg(long)]
    pub steps: Option<usize>,
    /// unipc | ddim (default: the model's)
    #[arg(long)]
    pub sampler: Option<String>,
    /// Reference guidance scale w (default: the model's; 1 = references without guidance)
    #[arg(long)]
    pub ref_guidance: Option<f64>,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// UNet/ControlNet dtype (the VAE runs in f32)
    #[arg(long, default_value = "f32")]
    pub dtype: DType,
    /// Drivable-area GeoJSON (global frame) for the drivable_area mask channel
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// How to read the keyframe's box z: auto, center or top (as `b2dr project`)
    #[arg(long, default_value = "auto")]
    pub box_z: String,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(device: Option<String>, a: RenderArgs) -> Result<()> {
    if let Some(w) = a.ref_guidance {
        b2dr::sampling::check_guidance("--ref-guidance", w)?;
    }
    let refs = match a.refs {
        Some(v) => {
            let [x, y]: [PathBuf; 2] = v
                .try_into()
                .map_err(|_| anyhow::anyhow!("--refs takes two keyframe JSON files"))?;
            Some([x, y])
        }
        None => None,
    };
    let ctx = Context::new(&ContextOptions {
        device,
        ..Default::default()
    })?;
    let report = job::run(
        &ctx,
        &RenderJob {
            model: a.model,
            frame: a.frame,
            prev: a.prev,
            refs,
            no_refs: a.no_refs,
            cameras: a.cameras,
            steps: a.steps,
            sampler: a.sampler,
            ref_guidance: a.ref_guidance,
            seed: a.seed,
            dtype: a.dtype,
            map: a.map,
            box_z: a.box_z,
            out: a.out.clone(),
        },
    )?;
    eprintln!(
        "wrote {}/<CAMERA>.png/.exr and render.json: {} cameras, encode {:.0} ms, denoise {:.0} ms, decode {:.0} ms",
        a.out.display(),
        report["cameras"].as_array().map(|c| c.len()).unwrap_or(0),
        report["times_ms"]["encode_ms"].as_f64().unwrap_or(0.0),
        report["times_ms"]["denoise_ms"].as_f64().unwrap_or(0.0),
        report["times_ms"]["decode_ms"].as_f64().unwrap_or(0.0),
    );
    Ok(())
}
