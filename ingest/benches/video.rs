//! `cargo bench -p ingest --bench video`: what `--images video` costs and saves (the figures in
//! ingest/README.md). For each camera set: the bytes of its frames stored as PNG (the store's own
//! PNGs, as `--images png` writes them) against the MP4s `--images video` writes, the encode rate
//! on one core (PNG decode + RGB→YUV + H.264 + MP4, as ingest runs it on the reader's thread), and
//! the frame error (PSNR of every frame decoded back with OpenH264 against the original).
//!
//! Inputs: the real robomimic renders of `fixtures/robomimic/lift_rollouts_image.hdf5` (84×84)
//! and an ALOHA-size episode written by `scripts/gen_aloha.py` (3 cameras at 480×640, 400 steps;
//! generated into the target directory, never into git; needs python3 with h5py and Pillow).
#![allow(
    clippy::unwrap_used,
    clippy::too_many_lines,
    reason = "benchmarks: a failed unwrap is a failed run, and a measurement reads top to bottom"
)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use ingest::model::Frames;
use ingest::sink::CollectSink;
use ingest::{Format, ReadOptions};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR").map(PathBuf::from).unwrap_or_else(|| repo().join("target"))
}

fn aloha_episode() -> Option<PathBuf> {
    let dir = target_dir().join("bench/video_aloha");
    let ep = dir.join("episode_0.hdf5");
    if ep.exists() {
        return Some(ep);
    }
    std::fs::create_dir_all(&dir).ok()?;
    eprintln!("generating {} (scripts/gen_aloha.py, 3 cameras 480x640, 400 steps) ...", ep.display());
    let st = Command::new("python3")
        .arg(repo().join("scripts/gen_aloha.py"))
        .arg(&dir)
        .args(["--episodes", "1", "--steps", "400", "--cameras", "3"])
        .status()
        .ok()?;
    (st.success() && ep.exists()).then_some(ep)
}

struct Figures {
    frames: usize,
    png_bytes: u64,
    mp4_bytes: u64,
    encode_secs: f64,
    psnr_min: f64,
    psnr_mean: f64,
}

fn measure(path: &Path, format: Format) -> Figures {
    let mut sink = CollectSink::default();
    ingest::read_path_report(path, format, &ReadOptions::default(), &mut sink).expect("read the source");
    let tmp = tempfile::tempdir().unwrap();
    let mut f = Figures {
        frames: 0,
        png_bytes: 0,
        mp4_bytes: 0,
        encode_secs: 0.0,
        psnr_min: f64::INFINITY,
        psnr_mean: 0.0,
    };
    let mut psnr_sum = 0.0;
    for (e, ep) in sink.episodes.iter_mut().enumerate() {
        for (c, im) in ep.images.iter_mut().enumerate() {
            let frames = std::mem::take(&mut im.frames).collect_encoded().expect("frames");
            f.png_bytes += frames.iter().map(|p| p.len() as u64).sum::<u64>();
            let out = tmp.path().join(format!("{e}_{c}.mp4"));
            let t = Instant::now();
            let video =
                ingest::video::encode_camera(&out, &im.name, Frames::Encoded(frames.clone()), &ep.timestamps)
                    .expect("encode")
                    .unwrap_or_else(|_| panic!("{} is not an 8-bit camera", im.name));
            f.encode_secs += t.elapsed().as_secs_f64();
            f.mp4_bytes += video.size_bytes;
            let mut t = 0;
            store::video::decode_all(std::fs::read(&video.path).unwrap(), |_, dec| {
                let (_, _, orig) = ingest::video::png_to_rgb(&frames[t]).unwrap().unwrap();
                let p = store::video::psnr(&orig, &dec.rgb);
                f.psnr_min = f.psnr_min.min(p);
                psnr_sum += p;
                t += 1;
            })
            .expect("decode");
            f.frames += t;
        }
    }
    f.psnr_mean = psnr_sum / f.frames.max(1) as f64;
    f
}

fn report(what: &str, f: &Figures) {
    println!(
        "{what}: {} frames; PNG {:.2} MB, MP4 {:.2} MB ({:.1}x smaller, {:.1}% of PNG); encode {:.1} frames/s on one core \
         (PNG decode + H.264 + MP4); PSNR min {:.1} dB, mean {:.1} dB",
        f.frames,
        f.png_bytes as f64 / 1e6,
        f.mp4_bytes as f64 / 1e6,
        f.png_bytes as f64 / f.mp4_bytes.max(1) as f64,
        100.0 * f.mp4_bytes as f64 / f.png_bytes.max(1) as f64,
        f.frames as f64 / f.encode_secs,
        f.psnr_min,
        f.psnr_mean,
    );
}

fn main() {
    let robomimic = repo().join("fixtures/robomimic/lift_rollouts_image.hdf5");
    report(
        "robomimic renders 84x84 (lift_rollouts_image.hdf5, 4 episodes)",
        &measure(&robomimic, Format::Robomimic),
    );
    match aloha_episode() {
        Some(ep) => {
            report("ALOHA-size 480x640 (gen_aloha.py, 1 episode x 3 cameras)", &measure(&ep, Format::Aloha))
        }
        None => eprintln!(
            "skipped the ALOHA-size figures: python3 with h5py and Pillow is needed to generate them"
        ),
    }
}
