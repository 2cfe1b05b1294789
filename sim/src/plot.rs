//! PNG plot of sample trajectories: panels side by side (e.g. demos | base | steered), each showing
//! the wall (grey), the gaps, the goal (green disc) and trajectories (green = success, red =
//! failure). Hand-rolled rasteriser on the `png` crate.
use crate::demos::Demo;
use crate::env::EnvConfig;
use crate::rollout::Episode;
use anyhow::Result;
use std::path::Path;

pub struct Panel<'a> {
    pub title: String,
    pub trajs: Vec<(&'a [[f32; 2]], bool)>,
}

impl<'a> Panel<'a> {
    pub fn from_episodes(title: &str, eps: &'a [Episode], max: usize) -> Self {
        Panel {
            title: title.into(),
            trajs: eps.iter().take(max).map(|e| (e.positions.as_slice(), e.success)).collect(),
        }
    }
    pub fn from_demos(title: &str, demos: &'a [Demo], max: usize) -> Self {
        Panel {
            title: title.into(),
            trajs: demos.iter().take(max).map(|d| (d.positions.as_slice(), true)).collect(),
        }
    }
}

struct Canvas {
    w: usize,
    h: usize,
    px: Vec<[f32; 3]>,
}

impl Canvas {
    fn blend(&mut self, x: i64, y: i64, c: [f32; 3], a: f32) {
        if x < 0 || y < 0 || x as usize >= self.w || y as usize >= self.h {
            return;
        }
        let p = &mut self.px[y as usize * self.w + x as usize];
        for k in 0..3 {
            p[k] = p[k] * (1.0 - a) + c[k] * a;
        }
    }
    fn rect(&mut self, x0: f32, y0: f32, x1: f32, y1: f32, c: [f32; 3]) {
        for y in y0.floor() as i64..=y1.ceil() as i64 {
            for x in x0.floor() as i64..=x1.ceil() as i64 {
                self.blend(x, y, c, 1.0);
            }
        }
    }
    fn disc(&mut self, cx: f32, cy: f32, r: f32, c: [f32; 3], a: f32) {
        for y in (cy - r).floor() as i64..=(cy + r).ceil() as i64 {
            for x in (cx - r).floor() as i64..=(cx + r).ceil() as i64 {
                let d = ((x as f32 - cx).powi(2) + (y as f32 - cy).powi(2)).sqrt();
                if d <= r {
                    self.blend(x, y, c, a);
                }
            }
        }
    }
    /// Line with a little thickness, alpha-blended.
    fn line(&mut self, a: [f32; 2], b: [f32; 2], c: [f32; 3], alpha: f32) {
        let len = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
        let n = (len * 2.0).ceil().max(1.0) as usize;
        for i in 0..=n {
            let t = i as f32 / n as f32;
            let x = a[0] + t * (b[0] - a[0]);
            let y = a[1] + t * (b[1] - a[1]);
            self.blend(x.round() as i64, y.round() as i64, c, alpha);
        }
    }
}

/// Write panels side by side, each `size` x `size` pixels, to `path`.
pub fn plot_panels(path: &Path, cfg: &EnvConfig, panels: &[Panel], size: usize) -> Result<()> {
    let gap = 8;
    let w = panels.len().max(1) * (size + gap) - gap;
    let h = size;
    let mut cv = Canvas { w, h, px: vec![[1.0; 3]; w * h] };
    for (pi, panel) in panels.iter().enumerate() {
        let ox = (pi * (size + gap)) as f32;
        let s = size as f32;
        let to = |p: [f32; 2]| [ox + p[0] * s, (1.0 - p[1]) * s];
        // frame
        for k in 0..size {
            for &(x, y) in
                &[(ox, k as f32), (ox + s - 1.0, k as f32), (ox + k as f32, 0.0), (ox + k as f32, s - 1.0)]
            {
                cv.blend(x as i64, y as i64, [0.3, 0.3, 0.3], 1.0);
            }
        }
        for r in cfg.wall_rects() {
            let a = to([r[0], r[3]]);
            let b = to([r[2], r[1]]);
            cv.rect(a[0], a[1], b[0], b[1], [0.35, 0.35, 0.35]);
        }
        let g = to(cfg.goal);
        cv.disc(g[0], g[1], cfg.goal_radius * s, [0.2, 0.75, 0.3], 0.35);
        let st = to(cfg.start);
        cv.disc(st[0], st[1], 4.0, [0.2, 0.3, 0.9], 0.8);
        let alpha = (12.0 / panel.trajs.len().max(1) as f32).clamp(0.15, 0.8);
        for (traj, ok) in &panel.trajs {
            let c = if *ok { [0.1, 0.6, 0.15] } else { [0.85, 0.1, 0.1] };
            for wdw in traj.windows(2) {
                cv.line(to(wdw[0]), to(wdw[1]), c, alpha);
            }
        }
    }
    let file = std::fs::File::create(path)?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut wr = enc.write_header()?;
    let data: Vec<u8> =
        cv.px.iter().flat_map(|p| p.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)).collect();
    wr.write_image_data(&data)?;
    Ok(())
}
