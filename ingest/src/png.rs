//! PNG encoding of raw u8 camera frames (robomimic and ALOHA cameras are stored as PNG).

/// PNG-encodes `t` frames of `h x w x c` u8 (fast compression), on two threads when it pays.
pub fn encode_png_frames(
    bytes: &[u8],
    t: usize,
    h: usize,
    w: usize,
    c: usize,
) -> std::result::Result<Vec<Vec<u8>>, String> {
    let frame = h * w * c;
    let enc = |chunk: &[u8]| -> std::result::Result<Vec<Vec<u8>>, String> {
        chunk.chunks(frame).map(|f| encode_png(f, h, w, c)).collect()
    };
    if t >= 8 && frame * t >= 1 << 20 {
        let half = t / 2;
        let (a, b) = bytes.split_at(half * frame);
        let (ra, rb) = std::thread::scope(|s| {
            let hb = s.spawn(|| enc(b));
            let ra = enc(a);
            (ra, hb.join())
        });
        let mut out = ra?;
        out.extend(rb.map_err(|_| "PNG encoder thread panicked".to_string())??);
        Ok(out)
    } else {
        enc(bytes)
    }
}

pub fn encode_png(frame: &[u8], h: usize, w: usize, c: usize) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(frame.len() / 2 + 64);
    {
        let mut e = png::Encoder::new(&mut out, w as u32, h as u32);
        e.set_color(match c {
            1 => png::ColorType::Grayscale,
            2 => png::ColorType::GrayscaleAlpha,
            3 => png::ColorType::Rgb,
            _ => png::ColorType::Rgba,
        });
        e.set_depth(png::BitDepth::Eight);
        e.set_compression(png::Compression::Fast);
        let mut wr = e.write_header().map_err(|e| format!("PNG encoding failed: {e}"))?;
        wr.write_image_data(frame).map_err(|e| format!("PNG encoding failed: {e}"))?;
        wr.finish().map_err(|e| format!("PNG encoding failed: {e}"))?;
    }
    Ok(out)
}
