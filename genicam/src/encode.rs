//! A GenICam buffer's pixels as the PNG file a session stores.
//!
//! `Mono8` and the 8-bit Bayer formats become 8-bit grey (Bayer data as the sensor gave it,
//! to be demosaicked by whoever reads it), `RGB8` 8-bit colour, `Mono16` and the unpacked
//! `Mono10`/`Mono12`/`Mono14` 16-bit grey (little-endian on the wire; the values kept as
//! the camera gave them, not shifted). Packed formats are refused with what to set instead.

use std::io::Cursor;

use image::{ExtendedColorType, ImageEncoder};

/// PNG bytes of a `width × height` image of pixel format `format` (GenICam name) in `data`.
pub fn png(width: u32, height: u32, format: &str, data: &[u8]) -> Result<Vec<u8>, String> {
    let pixels = width as usize * height as usize;
    let (bytes_per_px, colour) = match format {
        "Mono8" | "BayerRG8" | "BayerGR8" | "BayerGB8" | "BayerBG8" => (1, ExtendedColorType::L8),
        "RGB8" | "RGB8Packed" => (3, ExtendedColorType::Rgb8),
        "Mono10" | "Mono12" | "Mono14" | "Mono16" => (2, ExtendedColorType::L16),
        other => {
            return Err(format!(
                "pixel format {other} is not stored: set pixel_format to Mono8, Mono16 (or unpacked \
                 Mono10/12/14), RGB8 or an 8-bit Bayer format in the rig file"
            ))
        }
    };
    let want = pixels * bytes_per_px;
    if data.len() < want {
        return Err(format!(
            "a {width}×{height} {format} frame needs {want} bytes, the buffer holds {}",
            data.len()
        ));
    }
    // The wire's 16-bit samples are little-endian; the encoder takes them in this machine's
    // order (and writes PNG's big-endian itself).
    let samples: Vec<u8> = if bytes_per_px == 2 {
        data[..want].chunks_exact(2).flat_map(|b| u16::from_le_bytes([b[0], b[1]]).to_ne_bytes()).collect()
    } else {
        data[..want].to_vec()
    };
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(Cursor::new(&mut out))
        .write_image(&samples, width, height, colour)
        .map_err(|e| format!("encoding a {width}×{height} {format} frame: {e}"))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sixteen_bit_frames_keep_their_values() {
        let (w, h) = (5u32, 3u32);
        let values: Vec<u16> = (0..w * h).map(|i| (i * 4001) as u16).collect();
        let wire: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let bytes = png(w, h, "Mono16", &wire).unwrap();
        let img = image::load_from_memory(&bytes).unwrap().into_luma16();
        assert_eq!(img.dimensions(), (w, h));
        assert_eq!(img.into_raw(), values);
    }

    #[test]
    fn eight_bit_and_colour_frames() {
        let grey: Vec<u8> = (0..12).collect();
        let img = image::load_from_memory(&png(4, 3, "Mono8", &grey).unwrap()).unwrap().into_luma8();
        assert_eq!(img.into_raw(), grey);
        let rgb: Vec<u8> = (0..36).collect();
        let img = image::load_from_memory(&png(4, 3, "RGB8", &rgb).unwrap()).unwrap().into_rgb8();
        assert_eq!(img.into_raw(), rgb);
    }

    #[test]
    fn short_buffers_and_packed_formats_are_refused() {
        assert!(png(4, 3, "Mono16", &[0; 10]).unwrap_err().contains("needs 24 bytes, the buffer holds 10"));
        assert!(png(4, 3, "Mono12Packed", &[0; 100]).unwrap_err().contains("set pixel_format"));
    }
}
