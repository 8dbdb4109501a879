//! What the MetaImage and NRRD sequence readers share: bounded header-line reading, checked pixel-block
//! sizes, streaming decompression into a preallocated buffer, MF orientation normalisation and the
//! assembly of `Seq_FrameNNNN_*` fields into frames.

use std::collections::BTreeMap;
use std::io::{BufRead, Read};
use std::path::Path;

use super::sequence::{
    ElementType, FrameTransform, PixelData, TrackedFrame, TrackedSequence, mat4_from_row_major,
};
use crate::{Error, FormatProblem, Result};

/// Longest header line accepted. Real PLUS lines are < 300 bytes; anything near this is not a header.
pub(crate) const MAX_HEADER_LINE_BYTES: usize = 1 << 20;
/// Largest header accepted, so a file of endless short lines cannot exhaust memory either.
pub(crate) const MAX_HEADER_BYTES: u64 = 256 << 20;
/// Deflate cannot compress better than about 1032:1, so a stream of `n` bytes inflates to at most
/// `1032 * n` bytes; a header promising more than that is lying and is rejected before allocating.
const MAX_DEFLATE_RATIO: u64 = 1032;
/// Largest decompression buffer allocated before data arrives (a full 820 x 616 x 201 sweep is 100 MB).
const MAX_UPFRONT_BYTES: usize = 256 << 20;

/// How the pixel block is stored after the header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Compression {
    None,
    Zlib,
    Gzip,
}

/// Reads one header line (without the line ending, CR stripped). `Ok(None)` at end of file.
/// Lines longer than [`MAX_HEADER_LINE_BYTES`] are rejected.
pub(crate) fn read_header_line<R: BufRead>(
    reader: &mut R,
    path: &Path,
    consumed: &mut u64,
) -> Result<Option<Vec<u8>>> {
    let mut line = Vec::new();
    let n = reader
        .by_ref()
        .take(MAX_HEADER_LINE_BYTES as u64 + 1)
        .read_until(b'\n', &mut line)
        .map_err(|e| Error::io(path, e))?;
    if n == 0 {
        return Ok(None);
    }
    *consumed += n as u64;
    if *consumed > MAX_HEADER_BYTES {
        return Err(Error::format(
            path,
            FormatProblem::SizeMismatch,
            format!("header longer than {MAX_HEADER_BYTES} bytes"),
        ));
    }
    if line.last() == Some(&b'\n') {
        line.pop();
    } else if n > MAX_HEADER_LINE_BYTES {
        return Err(Error::format(
            path,
            FormatProblem::SizeMismatch,
            format!("header line longer than {MAX_HEADER_LINE_BYTES} bytes"),
        ));
    }
    if line.last() == Some(&b'\r') {
        line.pop();
    }
    Ok(Some(line))
}

/// Header text as UTF-8 (PLUS writes ASCII); anything else is corrupt.
pub(crate) fn line_to_str<'a>(line: &'a [u8], path: &Path) -> Result<&'a str> {
    std::str::from_utf8(line).map_err(|_| {
        Error::format(
            path,
            FormatProblem::Corrupt,
            "header line is not text (binary data before the end of the header?)",
        )
    })
}

/// Image geometry of a pixel block, already checked against overflow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Layout {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub frames: usize,
    pub element: ElementType,
    pub big_endian: bool,
}

impl Layout {
    /// Bytes of the whole block, or an error if the product overflows.
    pub fn total_bytes(&self, path: &Path) -> Result<u64> {
        let total = (self.width as u64)
            .checked_mul(self.height as u64)
            .and_then(|v| v.checked_mul(self.channels as u64))
            .and_then(|v| v.checked_mul(self.frames as u64))
            .and_then(|v| v.checked_mul(self.element.size_bytes() as u64))
            .filter(|&v| usize::try_from(v).is_ok());
        total.ok_or_else(|| {
            Error::format(
                path,
                FormatProblem::SizeMismatch,
                format!(
                    "image size {} x {} x {} frames x {} channels does not fit in memory",
                    self.width, self.height, self.frames, self.channels
                ),
            )
        })
    }
}

/// Reads the pixel block of `expected` bytes from `reader`, which holds `available` bytes from here to
/// the end of its file. Sizes are checked before anything is allocated; a compressed stream must yield
/// exactly `expected` bytes.
pub(crate) fn read_pixel_block<R: Read>(
    reader: R,
    available: u64,
    expected: u64,
    compression: Compression,
    compressed_size: Option<u64>,
    path: &Path,
) -> Result<Vec<u8>> {
    let expected_usize = usize::try_from(expected)
        .map_err(|_| Error::format(path, FormatProblem::SizeMismatch, "image data too large"))?;
    match compression {
        Compression::None => {
            if available < expected {
                return Err(Error::format(
                    path,
                    FormatProblem::Truncated,
                    format!(
                        "header promises {expected} bytes of pixel data but only {available} follow"
                    ),
                ));
            }
            let mut buf = crate::resources::try_zeroed_vec::<u8>(
                expected_usize,
                &format!("{}: the pixel data", path.display()),
            )?;
            let mut reader = reader;
            reader.read_exact(&mut buf).map_err(|e| {
                if e.kind() == std::io::ErrorKind::UnexpectedEof {
                    Error::format(path, FormatProblem::Truncated, "pixel data ends early")
                } else {
                    Error::io(path, e)
                }
            })?;
            Ok(buf)
        }
        Compression::Zlib | Compression::Gzip => {
            let stream_len = match compressed_size {
                Some(size) if size > available => {
                    return Err(Error::format(
                        path,
                        FormatProblem::Truncated,
                        format!(
                            "CompressedDataSize is {size} bytes but only {available} bytes follow"
                        ),
                    ));
                }
                Some(size) => size,
                None => available,
            };
            let ceiling = stream_len
                .saturating_mul(MAX_DEFLATE_RATIO)
                .saturating_add(64);
            if expected > ceiling {
                return Err(Error::format(
                    path,
                    FormatProblem::SizeMismatch,
                    format!(
                        "header promises {expected} bytes of pixel data but a {stream_len}-byte \
                         compressed stream cannot hold that much"
                    ),
                ));
            }
            let limited = reader.take(stream_len);
            match compression {
                Compression::Zlib => {
                    inflate_exact(flate2::read::ZlibDecoder::new(limited), expected, path)
                }
                _ => inflate_exact(flate2::read::MultiGzDecoder::new(limited), expected, path),
            }
        }
    }
}

/// Decompresses exactly `expected` bytes and checks the stream ends there. The buffer is allocated up
/// front (one copy-free pass) up to [`MAX_UPFRONT_BYTES`]; beyond that it grows only as real data
/// arrives, so a header that lies about the size cannot make us allocate what the stream does not hold.
fn inflate_exact<D: Read>(decoder: D, expected: u64, path: &Path) -> Result<Vec<u8>> {
    let upfront = usize::try_from(expected)
        .unwrap_or(usize::MAX)
        .min(MAX_UPFRONT_BYTES);
    let mut buf = Vec::new();
    buf.try_reserve_exact(upfront).map_err(|_| {
        Error::ResourceLimit(format!(
            "{}: could not allocate {upfront} bytes for the pixel data",
            path.display()
        ))
    })?;
    // One byte more than promised, to notice a stream that holds more.
    let mut limited = decoder.take(expected.saturating_add(1));
    loop {
        match limited.read_to_end(&mut buf) {
            Ok(_) => break,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {
                return Err(Error::format(
                    path,
                    FormatProblem::Truncated,
                    format!(
                        "compressed stream ends early after {} of {expected} bytes",
                        buf.len()
                    ),
                ));
            }
            Err(e) => {
                return Err(Error::format(
                    path,
                    FormatProblem::Corrupt,
                    format!("compressed pixel data does not decode: {e}"),
                ));
            }
        }
    }
    let got = buf.len() as u64;
    if got < expected {
        return Err(Error::format(
            path,
            FormatProblem::Truncated,
            format!(
                "compressed stream holds {got} bytes of pixel data, header promises {expected}"
            ),
        ));
    }
    if got > expected {
        return Err(Error::format(
            path,
            FormatProblem::SizeMismatch,
            format!("compressed stream holds more than the {expected} bytes the header promises"),
        ));
    }
    Ok(buf)
}

/// Flips to apply to bring an image of the given `UltrasoundImageOrientation` to MF:
/// (flip columns, flip rows). Accepts two or three letters (the third, A/D, is the out-of-plane axis).
pub(crate) fn orientation_flips(orientation: &str, path: &Path) -> Result<(bool, bool)> {
    let o = orientation.trim().to_ascii_uppercase();
    if o.is_empty() {
        return Ok((false, false));
    }
    let b = o.as_bytes();
    let ok_len = b.len() == 2 || (b.len() == 3 && matches!(b[2], b'A' | b'D'));
    if !ok_len {
        return Err(Error::format(
            path,
            FormatProblem::BadValue,
            format!("ultrasound image orientation {orientation:?} is not MF, MN, UF, UN (+A/D)"),
        ));
    }
    let flip_cols = match b[0] {
        b'M' => false,
        b'U' => true,
        _ => {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                format!("ultrasound image orientation {orientation:?}: first letter not M or U"),
            ));
        }
    };
    let flip_rows = match b[1] {
        b'F' => false,
        b'N' => true,
        _ => {
            return Err(Error::format(
                path,
                FormatProblem::BadValue,
                format!("ultrasound image orientation {orientation:?}: second letter not F or N"),
            ));
        }
    };
    Ok((flip_cols, flip_rows))
}

/// Flips every frame of a raw pixel block in place (pixels of `pixel_bytes` bytes each).
pub(crate) fn flip_frames(bytes: &mut [u8], layout: &Layout, flip_cols: bool, flip_rows: bool) {
    let px = layout.channels * layout.element.size_bytes();
    let row = layout.width * px;
    let frame = row * layout.height;
    if frame == 0 {
        return;
    }
    for f in bytes.chunks_exact_mut(frame) {
        if flip_rows {
            for r in 0..layout.height / 2 {
                let (top, bottom) = f.split_at_mut((layout.height - 1 - r) * row);
                top[r * row..(r + 1) * row].swap_with_slice(&mut bottom[..row]);
            }
        }
        if flip_cols {
            for r in f.chunks_exact_mut(row) {
                for c in 0..layout.width / 2 {
                    let (left, right) = r.split_at_mut((layout.width - 1 - c) * px);
                    left[c * px..(c + 1) * px].swap_with_slice(&mut right[..px]);
                }
            }
        }
    }
}

/// Typed pixels from raw bytes in the file's byte order.
pub(crate) fn bytes_to_pixels(bytes: Vec<u8>, element: ElementType, big_endian: bool) -> PixelData {
    macro_rules! conv {
        ($t:ty, $n:expr) => {
            bytes
                .chunks_exact($n)
                .map(|c| {
                    let a: [u8; $n] = c.try_into().expect("chunk size");
                    if big_endian {
                        <$t>::from_be_bytes(a)
                    } else {
                        <$t>::from_le_bytes(a)
                    }
                })
                .collect()
        };
    }
    match element {
        ElementType::U8 => PixelData::U8(bytes),
        ElementType::I8 => PixelData::I8(bytes.into_iter().map(|b| b as i8).collect()),
        ElementType::U16 => PixelData::U16(conv!(u16, 2)),
        ElementType::I16 => PixelData::I16(conv!(i16, 2)),
        ElementType::F32 => PixelData::F32(conv!(f32, 4)),
    }
}

/// `Seq_FrameNNNN_Name` -> (NNNN, Name).
pub(crate) fn split_frame_key(key: &str) -> Option<(usize, &str)> {
    let rest = key.strip_prefix("Seq_Frame")?;
    let digits = rest.bytes().take_while(u8::is_ascii_digit).count();
    if digits == 0 || digits > 9 {
        return None;
    }
    let index: usize = rest[..digits].parse().ok()?;
    let name = rest[digits..].strip_prefix('_')?;
    if name.is_empty() {
        return None;
    }
    Some((index, name))
}

/// Status text -> valid. Only `OK` counts; PLUS also writes INVALID, OUT_OF_VIEW, MISSING, ...
pub(crate) fn status_is_ok(value: &str) -> bool {
    value.trim().eq_ignore_ascii_case("OK")
}

/// Parses whitespace-separated finite numbers.
pub(crate) fn parse_numbers(value: &str) -> Option<Vec<f64>> {
    value
        .split_ascii_whitespace()
        .map(|t| t.parse::<f64>().ok())
        .collect()
}

/// Collects per-frame fields of a sequence file and builds the frames once the whole header is read.
#[derive(Debug, Default)]
pub(crate) struct FrameFieldCollector {
    /// (frame index, field name, value) in file order.
    entries: Vec<(usize, String, String)>,
}

impl FrameFieldCollector {
    pub fn push(&mut self, index: usize, name: &str, value: &str) {
        self.entries
            .push((index, name.to_string(), value.trim().to_string()));
    }

    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Builds `frame_count` frames. `image_status_names` are the field names that carry the image
    /// status (`ImageStatus`, and `Status` in NRRD files).
    pub fn build(
        self,
        frame_count: usize,
        image_status_names: &[&str],
        path: &Path,
    ) -> Result<Vec<TrackedFrame>> {
        if let Some((index, name, _)) = self.entries.iter().find(|(i, _, _)| *i >= frame_count) {
            return Err(Error::format(
                path,
                FormatProblem::SizeMismatch,
                format!(
                    "per-frame field Seq_Frame{index:04}_{name} but the image has {frame_count} frames"
                ),
            ));
        }
        let mut frames: Vec<TrackedFrame> = (0..frame_count)
            .map(|_| TrackedFrame {
                image_valid: true,
                ..TrackedFrame::default()
            })
            .collect();
        // Matrices are parsed after all statuses are known: a non-finite matrix is only an error when it
        // claims to be valid.
        let mut matrices: Vec<(usize, String, String)> = Vec::new();
        let mut statuses: BTreeMap<(usize, String), bool> = BTreeMap::new();
        for (index, name, value) in self.entries {
            let frame = &mut frames[index];
            if let Some(base) = name.strip_suffix("TransformStatus") {
                statuses.insert((index, base.to_string()), status_is_ok(&value));
            } else if let Some(base) = name.strip_suffix("Transform") {
                matrices.push((index, base.to_string(), value));
            } else if image_status_names.contains(&name.as_str()) {
                frame.image_valid = status_is_ok(&value);
            } else if name == "Timestamp" {
                let t: f64 = value
                    .parse()
                    .ok()
                    .filter(|t: &f64| t.is_finite())
                    .ok_or_else(|| {
                        Error::format(
                            path,
                            FormatProblem::BadValue,
                            format!(
                                "Seq_Frame{index:04}_Timestamp = {value:?} is not a finite number"
                            ),
                        )
                    })?;
                frame.timestamp_s = Some(t);
            } else {
                frame.fields.insert(name, value);
            }
        }
        for (index, base, value) in matrices {
            let valid = statuses
                .get(&(index, base.clone()))
                .copied()
                .unwrap_or(true);
            let numbers = parse_numbers(&value)
                .filter(|v| v.len() == 16)
                .ok_or_else(|| {
                    Error::format(
                        path,
                        FormatProblem::BadValue,
                        format!(
                            "Seq_Frame{index:04}_{base}Transform is not 16 numbers: {:?}",
                            truncate_for_message(&value)
                        ),
                    )
                })?;
            if valid && numbers.iter().any(|v| !v.is_finite()) {
                return Err(Error::format(
                    path,
                    FormatProblem::BadValue,
                    format!(
                        "Seq_Frame{index:04}_{base}Transform has non-finite entries but status OK"
                    ),
                ));
            }
            let array: [f64; 16] = numbers.try_into().expect("16 numbers");
            let matrix = mat4_from_row_major(&array);
            if valid && let Err(row) = super::plus_config::check_affine(&matrix) {
                return Err(Error::format(
                    path,
                    FormatProblem::BadValue,
                    format!(
                        "frame {index}: Seq_Frame{index:04}_{base}Transform is not affine: its \
                         bottom row is {} {} {} {}, not 0 0 0 1",
                        row[0], row[1], row[2], row[3]
                    ),
                ));
            }
            frames[index]
                .transforms
                .insert(base, FrameTransform { matrix, valid });
        }
        // A status without its matrix: keep the information as a plain field rather than drop it.
        for ((index, base), ok) in statuses {
            if !frames[index].transforms.contains_key(&base) {
                frames[index].fields.insert(
                    format!("{base}TransformStatus"),
                    if ok { "OK".into() } else { "INVALID".into() },
                );
            }
        }
        Ok(frames)
    }
}

pub(crate) fn truncate_for_message(value: &str) -> String {
    if value.len() <= 120 {
        value.to_string()
    } else {
        let mut end = 120;
        while !value.is_char_boundary(end) {
            end -= 1;
        }
        format!("{}...", &value[..end])
    }
}

/// Everything a reader has gathered, turned into a sequence (pixels decoded and brought to MF).
pub(crate) struct Assembled {
    pub layout: Layout,
    pub orientation: String,
    pub frames: Vec<TrackedFrame>,
    /// Raw pixel bytes in file orientation, or `None` for a tracking-only file.
    pub bytes: Option<Vec<u8>>,
    pub header: BTreeMap<String, String>,
}

pub(crate) fn assemble(a: Assembled, path: &Path) -> Result<TrackedSequence> {
    let (flip_cols, flip_rows) = orientation_flips(&a.orientation, path)?;
    let pixels = match a.bytes {
        Some(mut bytes) => {
            flip_frames(&mut bytes, &a.layout, flip_cols, flip_rows);
            bytes_to_pixels(bytes, a.layout.element, a.layout.big_endian)
        }
        None => empty_pixels(a.layout.element),
    };
    if let PixelData::F32(values) = &pixels {
        check_finite_pixels(
            values,
            a.layout.width * a.layout.height * a.layout.channels,
            path,
        )?;
    }
    Ok(TrackedSequence {
        width: a.layout.width,
        height: a.layout.height,
        channels: a.layout.channels,
        orientation: a.orientation,
        frames: a.frames,
        pixels,
        header: a.header,
    })
}

/// Refuses floating-point frames holding NaN or infinite pixels: no grey level stands for them, and
/// masking them would hide a broken recording. Names how many there are and the first frame with one.
fn check_finite_pixels(values: &[f32], frame_len: usize, path: &Path) -> Result<()> {
    let bad = values.iter().filter(|v| !v.is_finite()).count();
    if bad == 0 {
        return Ok(());
    }
    let first = values.iter().position(|v| !v.is_finite()).unwrap_or(0);
    Err(Error::format(
        path,
        FormatProblem::BadValue,
        format!(
            "{bad} of {} MET_FLOAT pixels are NaN or infinite (the first in frame {}); echosurf \
             refuses non-finite pixels rather than guess a grey level for them",
            values.len(),
            first / frame_len.max(1)
        ),
    ))
}

pub(crate) fn empty_pixels(element: ElementType) -> PixelData {
    match element {
        ElementType::U8 => PixelData::U8(Vec::new()),
        ElementType::I8 => PixelData::I8(Vec::new()),
        ElementType::U16 => PixelData::U16(Vec::new()),
        ElementType::I16 => PixelData::I16(Vec::new()),
        ElementType::F32 => PixelData::F32(Vec::new()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout(w: usize, h: usize, c: usize) -> Layout {
        Layout {
            width: w,
            height: h,
            channels: c,
            frames: 1,
            element: ElementType::U8,
            big_endian: false,
        }
    }

    #[test]
    fn flips_rows_and_columns() {
        // 3 x 2 image, values = 10 * row + column.
        let orig = vec![0u8, 1, 2, 10, 11, 12];
        let mut rows = orig.clone();
        flip_frames(&mut rows, &layout(3, 2, 1), false, true);
        assert_eq!(rows, vec![10, 11, 12, 0, 1, 2]);
        let mut cols = orig.clone();
        flip_frames(&mut cols, &layout(3, 2, 1), true, false);
        assert_eq!(cols, vec![2, 1, 0, 12, 11, 10]);
        let mut both = orig;
        flip_frames(&mut both, &layout(3, 2, 1), true, true);
        assert_eq!(both, vec![12, 11, 10, 2, 1, 0]);
    }

    #[test]
    fn flips_keep_channels_together() {
        let mut px = vec![1u8, 2, 3, 4];
        flip_frames(&mut px, &layout(2, 1, 2), true, false);
        assert_eq!(px, vec![3, 4, 1, 2]);
    }

    #[test]
    fn orientation_letters() {
        let p = Path::new("x.mha");
        assert_eq!(orientation_flips("MF", p).unwrap(), (false, false));
        assert_eq!(orientation_flips("MFA", p).unwrap(), (false, false));
        assert_eq!(orientation_flips("MN", p).unwrap(), (false, true));
        assert_eq!(orientation_flips("UF", p).unwrap(), (true, false));
        assert_eq!(orientation_flips("UNA", p).unwrap(), (true, true));
        assert_eq!(orientation_flips("", p).unwrap(), (false, false));
        assert_eq!(
            orientation_flips("XY", p).unwrap_err().problem(),
            Some(FormatProblem::BadValue)
        );
    }

    #[test]
    fn frame_keys() {
        assert_eq!(
            split_frame_key("Seq_Frame0012_ProbeToTrackerTransform"),
            Some((12, "ProbeToTrackerTransform"))
        );
        assert_eq!(split_frame_key("Seq_Frame_X"), None);
        assert_eq!(split_frame_key("Seq_Frame0001_"), None);
        assert_eq!(split_frame_key("Seq_Frame99999999999_A"), None);
    }

    #[test]
    fn big_endian_u16() {
        let px = bytes_to_pixels(vec![1, 2, 3, 4], ElementType::U16, true);
        assert_eq!(px, PixelData::U16(vec![0x0102, 0x0304]));
        let px = bytes_to_pixels(vec![1, 2, 3, 4], ElementType::U16, false);
        assert_eq!(px, PixelData::U16(vec![0x0201, 0x0403]));
    }

    #[test]
    fn header_line_limit() {
        let long = vec![b'a'; MAX_HEADER_LINE_BYTES + 10];
        let mut r = std::io::BufReader::new(&long[..]);
        let mut consumed = 0;
        let err = read_header_line(&mut r, Path::new("x"), &mut consumed).unwrap_err();
        assert_eq!(err.problem(), Some(FormatProblem::SizeMismatch));
        let mut r = std::io::BufReader::new(&b"A = 1\r\nB"[..]);
        assert_eq!(
            read_header_line(&mut r, Path::new("x"), &mut consumed).unwrap(),
            Some(b"A = 1".to_vec())
        );
    }

    #[test]
    fn zlib_stream_must_match_size() {
        use std::io::Write;
        let data = vec![7u8; 1000];
        let mut enc = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        enc.write_all(&data).unwrap();
        let z = enc.finish().unwrap();
        let p = Path::new("x");
        let n = z.len() as u64;
        let ok = read_pixel_block(&z[..], n, 1000, Compression::Zlib, Some(n), p).unwrap();
        assert_eq!(ok, data);
        let more = read_pixel_block(&z[..], n, 1001, Compression::Zlib, Some(n), p).unwrap_err();
        assert_eq!(more.problem(), Some(FormatProblem::Truncated));
        let less = read_pixel_block(&z[..], n, 999, Compression::Zlib, Some(n), p).unwrap_err();
        assert_eq!(less.problem(), Some(FormatProblem::SizeMismatch));
        let huge = read_pixel_block(&z[..], n, 1 << 40, Compression::Zlib, Some(n), p).unwrap_err();
        assert_eq!(huge.problem(), Some(FormatProblem::SizeMismatch));
    }
}
