//! A chunk's partial accumulation on the wire: an OpenEXR image whose channels are the integer
//! words of the fixed-point sums (so nothing is rounded), whose data window is the tile's
//! rectangle (tile plus filter margin) in image pixels, compressed with zstd.
//!
//! Channels (all 32-bit unsigned, sorted by name as EXR stores them): `R.0`..`R.3`, `G.*`,
//! `B.*` (filter-weighted radiance sums), `W.*` (weight sums), `L2.*` (sums of squared
//! luminance), each four words of a two's-complement 128-bit integer, least significant first;
//! `N.0`, `N.1` (sample count, 64 bits; dropped samples included). One custom header
//! attribute, `dropped` (text): the samples left out of the sums as three decimal counts,
//! "NAN INFINITE TOO_BRIGHT" (a partial without it dropped none); and optionally `stats`
//! (text): the chunk's [`RenderStats`](crate::RenderStats) as JSON. EXR carries no timestamps or
//! host names, so equal accumulations encode to equal bytes.

use std::io::Cursor;

use exr::prelude::*;
use furnace_core::Accum;

use crate::{pixel_from_words, pixel_words, WORDS};

const QUANTITIES: [&str; 5] = ["R", "G", "B", "W", "L2"];

#[derive(Debug, thiserror::Error)]
pub enum PartialError {
    #[error("partial is not zstd data: {0}")]
    Zstd(std::io::Error),
    #[error("partial is larger than {0} bytes once decompressed")]
    TooLarge(usize),
    #[error("partial is not a readable EXR: {0}")]
    Exr(String),
    #[error("partial EXR must have one layer with channels {expected}; found {found}")]
    Channels { expected: String, found: String },
    #[error("partial channel '{0}' must hold 32-bit unsigned integers")]
    ChannelType(String),
    #[error("partial attribute 'dropped' must be three decimal counts, found '{0}'")]
    Dropped(String),
    #[error("partial attribute 'stats' must be render statistics as JSON: {0}")]
    Stats(String),
}

/// The header attribute holding the chunk's render statistics.
const STATS: &str = "stats";

/// The header attribute holding the dropped-sample tallies.
const DROPPED: &str = "dropped";

/// The channels in the order EXR stores them (by name), each with its word's index in a pixel.
fn channel_order() -> Vec<(String, usize)> {
    let mut order: Vec<(String, usize)> = channel_names().into_iter().zip(0..).collect();
    order.sort();
    order
}

fn channel_names() -> Vec<String> {
    let mut names: Vec<String> =
        QUANTITIES.iter().flat_map(|q| (0..4).map(move |k| format!("{q}.{k}"))).collect();
    names.push("N.0".into());
    names.push("N.1".into());
    names
}

/// The most bytes a `width` x `height` partial decompresses to: its pixels' words, 16 bytes a
/// line (offset table entry and block header) and room for the EXR header.
pub fn partial_size_limit(width: u32, height: u32) -> usize {
    (width as usize * height as usize) * WORDS * 4 + height as usize * 16 + (64 << 10)
}

/// Encodes `acc` (zstd level 1 over an uncompressed EXR).
pub fn encode_partial(acc: &Accum) -> Vec<u8> {
    encode_chunk(acc, None)
}

/// Decodes a partial without its statistics; see [`decode_chunk`].
pub fn decode_partial(bytes: &[u8], max_bytes: usize) -> std::result::Result<Accum, PartialError> {
    decode_chunk(bytes, max_bytes).map(|(acc, _)| acc)
}

/// Encodes `acc` and, when given, the render statistics of the work that made it.
pub fn encode_chunk(acc: &Accum, stats: Option<&crate::RenderStats>) -> Vec<u8> {
    let mut out = Vec::new();
    write_chunk(acc, stats, &mut out).expect("writing to memory cannot fail");
    out
}

/// [`encode_chunk`] into `out`, a line at a time: besides `acc`, nothing but one line of it and
/// the compressor's window is held (a checkpoint of a large film is written straight to disk).
pub fn write_chunk(
    acc: &Accum,
    stats: Option<&crate::RenderStats>,
    out: &mut dyn std::io::Write,
) -> std::io::Result<()> {
    let head = exr_header(acc, stats)?;
    let mut z = zstd::Encoder::new(out, 1)?;
    // The frame records its size, as a one-shot compression's does: a decoder knows what it
    // needs (and refuses what is over its limit) before decompressing.
    z.include_contentsize(true)?;
    z.set_pledged_src_size(Some(exr_size(acc, &head)))?;
    write_exr(acc, &head, &mut std::io::BufWriter::with_capacity(1 << 16, &mut z))?;
    z.finish()?;
    Ok(())
}

/// Bytes of a line's block: its number, its size, its words.
fn block_size(acc: &Accum) -> usize {
    8 + acc.width as usize * WORDS * 4
}

/// Bytes of the EXR with header `head`.
fn exr_size(acc: &Accum, head: &[u8]) -> u64 {
    (head.len() + acc.height as usize * (8 + block_size(acc))) as u64
}

/// The header of the uncompressed, scan-line EXR of the format above: the attributes an
/// OpenEXR reader needs, in the order the `exr` crate writes them. An empty window has no
/// EXR.
fn exr_header(acc: &Accum, stats: Option<&crate::RenderStats>) -> std::io::Result<Vec<u8>> {
    if acc.width == 0 || acc.height == 0 {
        return Err(std::io::Error::new(std::io::ErrorKind::InvalidInput, "an empty partial has no EXR"));
    }
    fn attr(h: &mut Vec<u8>, name: &str, kind: &str, value: &[u8]) {
        for s in [name, kind] {
            h.extend_from_slice(s.as_bytes());
            h.push(0);
        }
        h.extend_from_slice(&(value.len() as i32).to_le_bytes());
        h.extend_from_slice(value);
    }
    let i32s = |v: &[i32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let h = acc.height as usize;
    let window = i32s(&[
        acc.x0 as i32,
        acc.y0 as i32,
        (acc.x0 + acc.width) as i32 - 1,
        (acc.y0 + acc.height) as i32 - 1,
    ]);
    let mut channels = Vec::new();
    for (name, _) in channel_order() {
        channels.extend_from_slice(name.as_bytes());
        // Unsigned int, linear, three reserved bytes, sampled every pixel.
        channels.extend_from_slice(&[0, 0, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0]);
    }
    channels.push(0);
    let mut head = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
    attr(&mut head, "chunkCount", "int", &i32s(&[h as i32]));
    attr(&mut head, "channels", "chlist", &channels);
    attr(&mut head, "compression", "compression", &[0]);
    attr(&mut head, "lineOrder", "lineOrder", &[0]);
    attr(&mut head, "displayWindow", "box2i", &window);
    attr(&mut head, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    attr(&mut head, "screenWindowCenter", "v2f", &[0; 8]);
    attr(&mut head, "screenWindowWidth", "float", &1f32.to_le_bytes());
    attr(&mut head, "dataWindow", "box2i", &window);
    attr(&mut head, "type", "string", b"scanlineimage");
    attr(&mut head, "name", "string", b"partial");
    let d = acc.dropped;
    attr(&mut head, DROPPED, "string", format!("{} {} {}", d.nan, d.infinite, d.too_bright).as_bytes());
    if let Some(s) = stats {
        attr(&mut head, STATS, "string", serde_json::to_string(s).expect("statistics serialise").as_bytes());
    }
    head.push(0);
    Ok(head)
}

/// Writes the EXR whose header is `head`: the header, the offset table, then one block a line,
/// each channel's words in channel-name order.
fn write_exr(acc: &Accum, head: &[u8], out: &mut impl std::io::Write) -> std::io::Result<()> {
    let (w, h) = (acc.width as usize, acc.height as usize);
    let order = channel_order();
    out.write_all(head)?;
    let block = block_size(acc);
    for y in 0..h {
        out.write_all(&((head.len() + h * 8 + y * block) as u64).to_le_bytes())?;
    }
    let (mut line, mut words) = (Vec::with_capacity(block), Vec::with_capacity(w));
    for (y, row) in acc.pixels.chunks_exact(w.max(1)).enumerate().take(h) {
        line.clear();
        line.extend_from_slice(&(acc.y0 as i32 + y as i32).to_le_bytes());
        line.extend_from_slice(&((w * WORDS * 4) as i32).to_le_bytes());
        words.clear();
        words.extend(row.iter().map(pixel_words));
        for &(_, k) in &order {
            line.extend(words.iter().flat_map(|p| p[k].to_le_bytes()));
        }
        out.write_all(&line)?;
    }
    out.flush()
}

/// Checks the EXR header before anything is decoded: one uncompressed, flat, scan-line
/// layer whose pixel data (22 words a pixel) fits in the bytes that came, so a small upload
/// whose header declares a huge data window allocates nothing.
fn check_header(exr: &[u8]) -> std::result::Result<(), PartialError> {
    let meta = exr::meta::MetaData::read_from_buffered(Cursor::new(exr), false)
        .map_err(|e| PartialError::Exr(e.to_string()))?;
    let [header] = meta.headers.as_slice() else {
        return Err(PartialError::Exr(format!("{} layers; a partial has one", meta.headers.len())));
    };
    let mut expected = channel_names();
    expected.sort();
    let found: Vec<String> = header.channels.list.iter().map(|c| c.name.to_string()).collect();
    if found != expected {
        return Err(PartialError::Channels { expected: expected.join(", "), found: found.join(", ") });
    }
    if header.compression != Compression::Uncompressed
        || header.deep
        || header.blocks != exr::meta::BlockDescription::ScanLines
    {
        return Err(PartialError::Exr("a partial is an uncompressed, flat, scan-line EXR".into()));
    }
    let (w, h) = (header.layer_size.width() as u64, header.layer_size.height() as u64);
    let need = w.checked_mul(h).and_then(|n| n.checked_mul(WORDS as u64 * 4));
    match need {
        Some(n) if n <= exr.len() as u64 => Ok(()),
        _ => Err(PartialError::Exr(format!(
            "its header declares {w} x {h} pixels, more than the {} bytes of the upload hold",
            exr.len()
        ))),
    }
}

/// Decodes a partial and its statistics (if it carries them), refusing anything that is not
/// exactly the format above or that would decompress past `max_bytes`.
pub fn decode_chunk(
    bytes: &[u8],
    max_bytes: usize,
) -> std::result::Result<(Accum, Option<crate::RenderStats>), PartialError> {
    let exr = zstd::bulk::decompress(bytes, max_bytes).map_err(|e| {
        if e.to_string().contains("too small") || e.to_string().contains("Destination buffer") {
            PartialError::TooLarge(max_bytes)
        } else {
            PartialError::Zstd(e)
        }
    })?;
    check_header(&exr)?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .non_parallel()
        .from_buffered(Cursor::new(exr))
        .map_err(|e| PartialError::Exr(e.to_string()))?;
    let names = channel_names();
    let mut sorted = names.clone();
    sorted.sort();
    let [layer] = image.layer_data.as_slice() else {
        return Err(PartialError::Channels {
            expected: sorted.join(", "),
            found: format!("{} layers", image.layer_data.len()),
        });
    };
    let found: Vec<String> = layer.channel_data.list.iter().map(|c| c.name.to_string()).collect();
    if found != sorted {
        return Err(PartialError::Channels { expected: sorted.join(", "), found: found.join(", ") });
    }
    let size = layer.size;
    let pos = layer.attributes.layer_position;
    if pos.0 < 0 || pos.1 < 0 {
        return Err(PartialError::Exr(format!("negative tile position {}, {}", pos.0, pos.1)));
    }
    let mut planes: Vec<&[u32]> = Vec::with_capacity(WORDS);
    for n in &names {
        let c = layer.channel_data.list.iter().find(|c| c.name.to_string() == *n).expect("checked above");
        match &c.sample_data {
            FlatSamples::U32(v) => planes.push(v),
            _ => return Err(PartialError::ChannelType(n.clone())),
        }
    }
    let count = size.0 * size.1;
    let mut acc = Accum::new(pos.0 as u32, pos.1 as u32, size.0 as u32, size.1 as u32);
    if let Some(v) = layer.attributes.other.get(&Text::new_or_panic(DROPPED)) {
        let text = match v {
            AttributeValue::Text(t) => t.to_string(),
            other => format!("{other:?}"),
        };
        let n: Option<Vec<u64>> = text.split(' ').map(|t| t.parse().ok()).collect();
        let Some([nan, infinite, too_bright]) = n.as_deref().and_then(|n| <[u64; 3]>::try_from(n).ok())
        else {
            return Err(PartialError::Dropped(text));
        };
        acc.dropped = furnace_core::Dropped { nan, infinite, too_bright };
    }
    let stats = match layer.attributes.other.get(&Text::new_or_panic(STATS)) {
        None => None,
        Some(AttributeValue::Text(t)) => {
            Some(serde_json::from_str(&t.to_string()).map_err(|e| PartialError::Stats(e.to_string()))?)
        }
        Some(other) => return Err(PartialError::Stats(format!("not text: {other:?}"))),
    };
    for i in 0..count {
        let mut w = [0u32; WORDS];
        for (k, plane) in planes.iter().enumerate() {
            w[k] = plane[i];
        }
        acc.pixels[i] = pixel_from_words(&w);
    }
    if acc.dropped.total() > acc.sample_count() {
        return Err(PartialError::Dropped(format!(
            "{} (more than the {} samples)",
            acc.dropped,
            acc.sample_count()
        )));
    }
    Ok((acc, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use furnace_core::film::PixelSum;

    #[test]
    fn partials_round_trip_exactly_and_encode_deterministically() {
        let mut acc = Accum::new(64, 128, 3, 2);
        for (i, p) in acc.pixels.iter_mut().enumerate() {
            *p = PixelSum {
                rgb: [i as i128 * 1_000_000_007, -(1i128 << 100) + i as i128, i128::MAX - i as i128],
                weight: 1i128 << 70,
                lum2: -5,
                count: u64::MAX - i as u64,
            };
        }
        acc.dropped = furnace_core::Dropped { nan: 1, infinite: u64::MAX / 8, too_bright: 3 };
        let bytes = encode_partial(&acc);
        assert_eq!(bytes, encode_partial(&acc), "same accumulation, same bytes");
        let back = decode_partial(&bytes, 1 << 20).unwrap();
        assert!(back == acc);
    }

    /// The EXR the `exr` crate writes for a partial (what `encode_chunk` was before it wrote
    /// the file itself, a line at a time).
    fn crate_exr(acc: &Accum) -> Vec<u8> {
        let mut names = channel_names();
        let mut planes: Vec<Vec<u32>> = vec![Vec::new(); WORDS];
        for p in &acc.pixels {
            for (plane, w) in planes.iter_mut().zip(pixel_words(p)) {
                plane.push(w);
            }
        }
        let channels: SmallVec<[AnyChannel<FlatSamples>; 4]> = names
            .drain(..)
            .zip(planes)
            .map(|(n, v)| AnyChannel::new(n.as_str(), FlatSamples::U32(v)))
            .collect();
        let mut attributes = LayerAttributes {
            layer_position: Vec2(acc.x0 as i32, acc.y0 as i32),
            ..LayerAttributes::named("partial")
        };
        let d = acc.dropped;
        let tallies = Text::new_or_panic(format!("{} {} {}", d.nan, d.infinite, d.too_bright));
        attributes.other.insert(Text::new_or_panic(DROPPED), AttributeValue::Text(tallies));
        let size = (acc.width as usize, acc.height as usize);
        let layer = Layer::new(size, attributes, Encoding::UNCOMPRESSED, AnyChannels::sort(channels));
        let mut exr = Vec::new();
        Image::from_layer(layer).write().non_parallel().to_buffered(Cursor::new(&mut exr)).unwrap();
        exr
    }

    /// The partial written a line at a time is the very file the `exr` crate writes, and reads.
    #[test]
    fn partials_written_by_line_are_the_exr_crates_bytes() {
        for (x0, y0, w, h) in [(0, 0, 1, 1), (64, 128, 3, 2), (5, 7, 17, 9), (0, 3, 1, 40)] {
            let mut acc = Accum::new(x0, y0, w, h);
            for (i, p) in acc.pixels.iter_mut().enumerate() {
                p.rgb = [i as i128 - 7, (i as i128) << 90, -(i as i128) << 40];
                p.weight = i as i128 * 3;
                p.lum2 = i128::MIN + i as i128;
                p.count = (i as u64) << 33 | 5;
            }
            acc.dropped.too_bright = 3;
            let mut ours = Vec::new();
            write_exr(&acc, &exr_header(&acc, None).unwrap(), &mut ours).unwrap();
            assert!(ours == crate_exr(&acc), "{w} x {h} at {x0}, {y0}");
            let stats = crate::RenderStats { rays: 42, ..Default::default() };
            let (back, st) = decode_chunk(&encode_chunk(&acc, Some(&stats)), 1 << 20).unwrap();
            assert!(back == acc && st == Some(stats));
        }
    }

    #[test]
    fn garbage_and_foreign_exrs_are_refused() {
        assert!(matches!(decode_partial(b"not zstd at all", 1 << 20), Err(PartialError::Zstd(_))));
        let not_exr = zstd::bulk::compress(b"hello", 1).unwrap();
        assert!(matches!(decode_partial(&not_exr, 1 << 20), Err(PartialError::Exr(_))));
        // An RGB float EXR full of NaN: wrong channels.
        let channels = SpecificChannels::rgb(|_: Vec2<usize>| (f32::NAN, f32::NAN, f32::NAN));
        let mut exr = Vec::new();
        Image::from_channels((4, 4), channels)
            .write()
            .non_parallel()
            .to_buffered(Cursor::new(&mut exr))
            .unwrap();
        let nan = zstd::bulk::compress(&exr, 1).unwrap();
        assert!(matches!(decode_partial(&nan, 1 << 20), Err(PartialError::Channels { .. })));
        // A tiny upload whose header declares a 60000 x 60000 data window: refused from the
        // header, before anything is allocated for its pixels.
        let huge = crate::fuzz::partial_declaring(60_000, 60_000);
        assert!(huge.len() < 1000, "{} bytes", huge.len());
        match decode_partial(&huge, 1 << 20) {
            Err(PartialError::Exr(e)) => assert!(e.contains("60000 x 60000"), "{e}"),
            other => panic!("{other:?}"),
        }
        // Bigger than allowed once decompressed; what a partial needs is allowed.
        let big = encode_partial(&Accum::new(0, 0, 64, 64));
        assert!(decode_partial(&big, partial_size_limit(64, 64)).is_ok());
        // A tall, narrow one too (16 bytes of table and block header a line).
        let tall = encode_partial(&Accum::new(0, 0, 1, 9000));
        assert!(decode_partial(&tall, partial_size_limit(1, 9000)).is_ok());
        assert!(matches!(decode_partial(&big, 1000), Err(PartialError::TooLarge(_))));
    }
}
