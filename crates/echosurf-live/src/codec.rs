//! The OpenIGTLink wire format (protocol versions 1-3): the 58-byte big-endian header with its
//! CRC-64, the v2/v3 extended header and metadata, and the IMAGE, TRANSFORM, STRING, STATUS and
//! POLYDATA bodies. Every length read from the wire is checked against the bytes actually there (and a
//! body against [`Limits::max_body_bytes`] before it is read), so bad bytes give a [`CodecError`],
//! never a panic or an allocation sized by an unchecked header.

use std::io::Read;

use glam::{DMat4, DVec3, DVec4};

use crate::crc64::crc64;

/// Size of the fixed message header.
pub const HEADER_SIZE: usize = 58;
/// Size of the v2/v3 extended header this codec writes (the smallest the spec allows).
pub const EXTENDED_HEADER_SIZE: usize = 12;
/// Size of the IMAGE body's own header (image header version 1).
pub const IMAGE_HEADER_SIZE: usize = 72;
/// Size of a TRANSFORM body: 12 big-endian floats.
pub const TRANSFORM_BODY_SIZE: usize = 48;
/// Size of the POLYDATA body's header: 10 u32 counts and sizes.
pub const POLYDATA_HEADER_SIZE: usize = 40;

/// Bounds on what the reader accepts from the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// A message whose header announces a larger body is refused before its body is read.
    pub max_body_bytes: u64,
}

impl Default for Limits {
    /// 64 MiB: a 2048 x 2048 RGBA float frame; B-mode frames are well under 1 MiB.
    fn default() -> Self {
        Limits {
            max_body_bytes: 64 << 20,
        }
    }
}

/// What is wrong with a message.
#[derive(Debug, thiserror::Error)]
pub enum CodecError {
    /// The header cannot be a header: the stream's framing is lost (the caller must reconnect).
    #[error("malformed header: {0}")]
    Header(String),
    /// The announced body is over the limit: not read, and the stream's framing is lost.
    #[error(
        "{type_name} message from {device_name:?} announces a body of {size} bytes, over the limit of {limit}"
    )]
    BodyTooLarge {
        type_name: String,
        device_name: String,
        size: u64,
        limit: u64,
    },
    /// The body arrived whole but its CRC-64 differs from the header's: the message is dropped.
    #[error(
        "{type_name} message from {device_name:?}: CRC-64 {computed:#018x} of the body, header says {expected:#018x}"
    )]
    Crc {
        type_name: String,
        device_name: String,
        expected: u64,
        computed: u64,
    },
    /// The body's content does not fit its type: the message is dropped.
    #[error("{type_name} message: {reason}")]
    Content { type_name: String, reason: String },
    /// The connection failed or closed (mid-message or between messages).
    #[error("connection: {0}")]
    Io(#[from] std::io::Error),
}

impl CodecError {
    /// Whether the stream can go on after this error (the message's bytes were all consumed).
    pub fn framing_intact(&self) -> bool {
        matches!(self, CodecError::Crc { .. } | CodecError::Content { .. })
    }

    fn content(type_name: &str, reason: impl Into<String>) -> CodecError {
        CodecError::Content {
            type_name: type_name.to_string(),
            reason: reason.into(),
        }
    }
}

/// The fixed 58-byte header.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Header {
    pub version: u16,
    pub type_name: String,
    pub device_name: String,
    /// Seconds since 1970 in the high 32 bits, the fraction of a second (units of 2^-32 s) in the low.
    pub timestamp: u64,
    pub body_size: u64,
    pub crc: u64,
}

impl Header {
    /// The timestamp in seconds.
    pub fn timestamp_s(&self) -> f64 {
        (self.timestamp >> 32) as f64 + (self.timestamp & 0xFFFF_FFFF) as f64 / 4_294_967_296.0
    }

    /// Parses a header. A version outside 1-3, or a type or device name that is not printable ASCII
    /// padded with NULs, is an error: they mean the bytes are not at a message boundary.
    pub fn decode(bytes: &[u8; HEADER_SIZE]) -> Result<Header, CodecError> {
        let version = u16::from_be_bytes([bytes[0], bytes[1]]);
        if !(1..=3).contains(&version) {
            return Err(CodecError::Header(format!(
                "protocol version {version} (expected 1, 2 or 3)"
            )));
        }
        let type_name = name_field(&bytes[2..14], "type")?;
        if type_name.is_empty() {
            return Err(CodecError::Header("empty message type".into()));
        }
        let device_name = name_field(&bytes[14..34], "device")?;
        Ok(Header {
            version,
            type_name,
            device_name,
            timestamp: be_u64(&bytes[34..42]),
            body_size: be_u64(&bytes[42..50]),
            crc: be_u64(&bytes[50..58]),
        })
    }
}

/// A name field: printable ASCII, then NUL padding only.
fn name_field(bytes: &[u8], what: &str) -> Result<String, CodecError> {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    if bytes[end..].iter().any(|&b| b != 0)
        || !bytes[..end].iter().all(|b| (0x20..0x7f).contains(b))
    {
        return Err(CodecError::Header(format!(
            "{what} name is not NUL-padded printable ASCII"
        )));
    }
    Ok(String::from_utf8_lossy(&bytes[..end]).into_owned())
}

fn be_u16(b: &[u8]) -> u16 {
    u16::from_be_bytes([b[0], b[1]])
}
fn be_u32(b: &[u8]) -> u32 {
    u32::from_be_bytes([b[0], b[1], b[2], b[3]])
}
fn be_u64(b: &[u8]) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[..8]);
    u64::from_be_bytes(a)
}
fn be_f32(b: &[u8]) -> f32 {
    f32::from_be_bytes([b[0], b[1], b[2], b[3]])
}

/// A whole message as read: header and body bytes (CRC checked).
#[derive(Debug, Clone, PartialEq)]
pub struct RawMessage {
    pub header: Header,
    pub body: Vec<u8>,
}

/// Reads one message: header, then (if the announced size is within `limits`) exactly that many body
/// bytes, then checks the CRC. A CRC error leaves the stream at the next message.
pub fn read_message(reader: &mut impl Read, limits: &Limits) -> Result<RawMessage, CodecError> {
    let mut header_bytes = [0u8; HEADER_SIZE];
    reader.read_exact(&mut header_bytes)?;
    let header = Header::decode(&header_bytes)?;
    if header.body_size > limits.max_body_bytes {
        return Err(CodecError::BodyTooLarge {
            type_name: header.type_name,
            device_name: header.device_name,
            size: header.body_size,
            limit: limits.max_body_bytes,
        });
    }
    // The size is bounded by the limit above; read_to_end grows the buffer only as bytes arrive.
    let mut body = Vec::new();
    reader
        .by_ref()
        .take(header.body_size)
        .read_to_end(&mut body)?;
    if body.len() as u64 != header.body_size {
        return Err(CodecError::Io(std::io::Error::new(
            std::io::ErrorKind::UnexpectedEof,
            format!(
                "the connection closed {} bytes into a {}-byte {} body",
                body.len(),
                header.body_size,
                header.type_name
            ),
        )));
    }
    let computed = crc64(&body);
    if computed != header.crc {
        return Err(CodecError::Crc {
            type_name: header.type_name,
            device_name: header.device_name,
            expected: header.crc,
            computed,
        });
    }
    Ok(RawMessage { header, body })
}

/// The part of a body that holds the message's content, and the v2/v3 metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct SplitBody<'a> {
    pub content: &'a [u8],
    pub metadata: Vec<(String, String)>,
    pub message_id: u32,
}

/// Splits a body into content and metadata (version 1 bodies are all content).
pub fn split_body<'a>(header: &Header, body: &'a [u8]) -> Result<SplitBody<'a>, CodecError> {
    let t = header.type_name.as_str();
    if header.version < 2 {
        return Ok(SplitBody {
            content: body,
            metadata: Vec::new(),
            message_id: 0,
        });
    }
    if body.len() < EXTENDED_HEADER_SIZE {
        return Err(CodecError::content(
            t,
            format!(
                "{}-byte body is shorter than the extended header",
                body.len()
            ),
        ));
    }
    let ext_size = be_u16(&body[0..2]) as usize;
    let meta_header_size = be_u16(&body[2..4]) as usize;
    let meta_size = be_u32(&body[4..8]) as usize;
    let message_id = be_u32(&body[8..12]);
    if ext_size < EXTENDED_HEADER_SIZE {
        return Err(CodecError::content(
            t,
            format!("extended header size {ext_size} is below {EXTENDED_HEADER_SIZE}"),
        ));
    }
    let tail = meta_header_size
        .checked_add(meta_size)
        .filter(|&n| n.checked_add(ext_size).is_some_and(|all| all <= body.len()))
        .ok_or_else(|| {
            CodecError::content(
                t,
                format!(
                    "extended header ({ext_size}) + metadata ({meta_header_size} + {meta_size}) \
                     bytes exceed the {}-byte body",
                    body.len()
                ),
            )
        })?;
    let content = &body[ext_size..body.len() - tail];
    let metadata = parse_metadata(t, &body[body.len() - tail..], meta_header_size)?;
    Ok(SplitBody {
        content,
        metadata,
        message_id,
    })
}

/// The metadata block: a u16 count, that many (key size u16, encoding u16, value size u32) entries,
/// then the keys and values in order.
fn parse_metadata(
    t: &str,
    block: &[u8],
    header_size: usize,
) -> Result<Vec<(String, String)>, CodecError> {
    if block.is_empty() {
        return Ok(Vec::new());
    }
    if header_size < 2 {
        return Err(CodecError::content(
            t,
            "metadata header shorter than its count",
        ));
    }
    let count = be_u16(&block[0..2]) as usize;
    if 2 + 8 * count > header_size {
        return Err(CodecError::content(
            t,
            format!("{count} metadata entries do not fit a {header_size}-byte metadata header"),
        ));
    }
    let mut entries = Vec::with_capacity(count);
    let mut at = header_size;
    for k in 0..count {
        let e = &block[2 + 8 * k..10 + 8 * k];
        let key_size = be_u16(&e[0..2]) as usize;
        let value_size = be_u32(&e[4..8]) as usize;
        let key_end = at.checked_add(key_size).filter(|&n| n <= block.len());
        let value_end = key_end
            .and_then(|n| n.checked_add(value_size))
            .filter(|&n| n <= block.len());
        let (Some(key_end), Some(value_end)) = (key_end, value_end) else {
            return Err(CodecError::content(
                t,
                format!("metadata entry {k} runs past the end of the body"),
            ));
        };
        let key = String::from_utf8_lossy(&block[at..key_end]).into_owned();
        let value = String::from_utf8_lossy(&block[key_end..value_end]).into_owned();
        entries.push((key, value));
        at = value_end;
    }
    Ok(entries)
}

/// IMAGE scalar types and their sizes in bytes.
pub fn scalar_size_bytes(scalar_type: u8) -> Option<usize> {
    match scalar_type {
        2 | 3 => Some(1),
        4 | 5 => Some(2),
        6 | 7 | 10 => Some(4),
        11 => Some(8),
        _ => None,
    }
}

/// OpenIGTLink's code for unsigned 8-bit pixels.
pub const SCALAR_UINT8: u8 = 3;

/// An IMAGE message's content (image header version 1; subvolumes are refused).
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    pub components: u8,
    pub scalar_type: u8,
    /// Pixel data byte order: true for big endian.
    pub big_endian: bool,
    /// 1: RAS, 2: LPS (kept as sent; the matrix is used as it is).
    pub coordinate: u8,
    /// Pixels along i, j, k.
    pub size: [u16; 3],
    /// The i, j, k axes in mm (direction times spacing), as sent.
    pub axes_mm: [[f32; 3]; 3],
    /// The world position of the image's centre (the middle of pixel (size - 1) / 2), as sent.
    pub centre_mm: [f32; 3],
    /// `size[0] * size[1] * size[2] * components` values, i fastest.
    pub pixels: Vec<u8>,
}

impl Image {
    /// Pixel (i, j, k) -> world: the axes as columns, the origin moved from the image centre to pixel 0.
    pub fn ijk_to_world(&self) -> DMat4 {
        let axes = self
            .axes_mm
            .map(|a| DVec3::new(a[0] as f64, a[1] as f64, a[2] as f64));
        let centre = DVec3::new(
            self.centre_mm[0] as f64,
            self.centre_mm[1] as f64,
            self.centre_mm[2] as f64,
        );
        let half = self.size.map(|n| (n as f64 - 1.0) / 2.0);
        let origin = centre - axes[0] * half[0] - axes[1] * half[1] - axes[2] * half[2];
        DMat4::from_cols(
            axes[0].extend(0.0),
            axes[1].extend(0.0),
            axes[2].extend(0.0),
            origin.extend(1.0),
        )
    }

    pub fn decode(content: &[u8]) -> Result<Image, CodecError> {
        let t = "IMAGE";
        if content.len() < IMAGE_HEADER_SIZE {
            return Err(CodecError::content(
                t,
                format!(
                    "{} bytes, shorter than the {IMAGE_HEADER_SIZE}-byte image header",
                    content.len()
                ),
            ));
        }
        let image_header_version = be_u16(&content[0..2]);
        if image_header_version != 1 {
            return Err(CodecError::content(
                t,
                format!("image header version {image_header_version} (expected 1)"),
            ));
        }
        let components = content[2];
        let scalar_type = content[3];
        let endian = content[4];
        let coordinate = content[5];
        let size = [0, 1, 2].map(|a| be_u16(&content[6 + 2 * a..]));
        let f = |k: usize| be_f32(&content[12 + 4 * k..]);
        let axes_mm = [0, 1, 2].map(|a| [f(3 * a), f(3 * a + 1), f(3 * a + 2)]);
        let centre_mm = [f(9), f(10), f(11)];
        let offset = [0, 1, 2].map(|a| be_u16(&content[60 + 2 * a..]));
        let sub_size = [0, 1, 2].map(|a| be_u16(&content[66 + 2 * a..]));
        let scalar = scalar_size_bytes(scalar_type)
            .ok_or_else(|| CodecError::content(t, format!("unknown scalar type {scalar_type}")))?;
        if components == 0 {
            return Err(CodecError::content(t, "0 components per pixel"));
        }
        if !matches!(endian, 1 | 2) {
            return Err(CodecError::content(
                t,
                format!("endianness code {endian} (expected 1 or 2)"),
            ));
        }
        if offset != [0, 0, 0] || sub_size != size {
            return Err(CodecError::content(
                t,
                format!(
                    "subvolume {offset:?} + {sub_size:?} of {size:?}: only whole images are taken"
                ),
            ));
        }
        if axes_mm
            .iter()
            .flatten()
            .chain(&centre_mm)
            .any(|v| !v.is_finite())
        {
            return Err(CodecError::content(
                t,
                "non-finite entries in the image matrix",
            ));
        }
        let expected = size
            .iter()
            .fold(components as u64 * scalar as u64, |n, &s| n * s as u64);
        let pixels = &content[IMAGE_HEADER_SIZE..];
        if pixels.len() as u64 != expected {
            return Err(CodecError::content(
                t,
                format!(
                    "{size:?} pixels x {components} x {scalar} bytes need {expected} bytes, the body has {}",
                    pixels.len()
                ),
            ));
        }
        Ok(Image {
            components,
            scalar_type,
            big_endian: endian == 1,
            coordinate,
            size,
            axes_mm,
            centre_mm,
            pixels: pixels.to_vec(),
        })
    }

    /// The content bytes (image header version 1, whole image).
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(IMAGE_HEADER_SIZE + self.pixels.len());
        out.extend_from_slice(&1u16.to_be_bytes());
        out.extend_from_slice(&[
            self.components,
            self.scalar_type,
            if self.big_endian { 1 } else { 2 },
            self.coordinate,
        ]);
        for s in self.size {
            out.extend_from_slice(&s.to_be_bytes());
        }
        for v in self.axes_mm.iter().flatten().chain(&self.centre_mm) {
            out.extend_from_slice(&v.to_be_bytes());
        }
        for s in [0, 0, 0].into_iter().chain(self.size) {
            out.extend_from_slice(&s.to_be_bytes());
        }
        out.extend_from_slice(&self.pixels);
        out
    }

    /// A single-component 8-bit 2D frame placed by `ijk_to_world` (axes with spacing, origin at pixel
    /// 0), as a sender would encode it (the centre from the origin, in f32 as on the wire).
    pub fn from_u8_frame(width: u16, height: u16, pixels: Vec<u8>, ijk_to_world: &DMat4) -> Image {
        let col = |c: DVec4| [c.x as f32, c.y as f32, c.z as f32];
        let centre = ijk_to_world.transform_point3(DVec3::new(
            (width as f64 - 1.0) / 2.0,
            (height as f64 - 1.0) / 2.0,
            0.0,
        ));
        Image {
            components: 1,
            scalar_type: SCALAR_UINT8,
            big_endian: false,
            coordinate: 1,
            size: [width, height, 1],
            axes_mm: [
                col(ijk_to_world.x_axis),
                col(ijk_to_world.y_axis),
                col(ijk_to_world.z_axis),
            ],
            centre_mm: [centre.x as f32, centre.y as f32, centre.z as f32],
            pixels,
        }
    }
}

/// A TRANSFORM message's matrix (the upper 3 x 4 of an affine transform).
pub fn decode_transform(content: &[u8]) -> Result<DMat4, CodecError> {
    if content.len() != TRANSFORM_BODY_SIZE {
        return Err(CodecError::content(
            "TRANSFORM",
            format!("{} bytes (expected {TRANSFORM_BODY_SIZE})", content.len()),
        ));
    }
    let v: Vec<f64> = (0..12).map(|k| be_f32(&content[4 * k..]) as f64).collect();
    if v.iter().any(|x| !x.is_finite()) {
        return Err(CodecError::content(
            "TRANSFORM",
            "non-finite matrix entries",
        ));
    }
    Ok(DMat4::from_cols(
        DVec4::new(v[0], v[1], v[2], 0.0),
        DVec4::new(v[3], v[4], v[5], 0.0),
        DVec4::new(v[6], v[7], v[8], 0.0),
        DVec4::new(v[9], v[10], v[11], 1.0),
    ))
}

/// The content bytes of a TRANSFORM message (entries rounded to f32 as the wire carries them).
pub fn encode_transform(matrix: &DMat4) -> Vec<u8> {
    let cols = [matrix.x_axis, matrix.y_axis, matrix.z_axis, matrix.w_axis];
    cols.iter()
        .flat_map(|c| [c.x, c.y, c.z])
        .flat_map(|v| (v as f32).to_be_bytes())
        .collect()
}

/// A STRING message's text (decoded lossily whatever its declared encoding).
pub fn decode_string(content: &[u8]) -> Result<String, CodecError> {
    if content.len() < 4 {
        return Err(CodecError::content(
            "STRING",
            "shorter than its 4-byte header",
        ));
    }
    let len = be_u16(&content[2..4]) as usize;
    let text = content.get(4..4 + len).ok_or_else(|| {
        CodecError::content(
            "STRING",
            format!("declares {len} bytes of text, has {}", content.len() - 4),
        )
    })?;
    Ok(String::from_utf8_lossy(text).into_owned())
}

/// The content bytes of a STRING message (UTF-8, MIBenum 106); text over 65535 bytes is cut.
pub fn encode_string(text: &str) -> Vec<u8> {
    let mut bytes = text.as_bytes();
    if bytes.len() > u16::MAX as usize {
        bytes = &bytes[..u16::MAX as usize];
    }
    let mut out = Vec::with_capacity(4 + bytes.len());
    out.extend_from_slice(&106u16.to_be_bytes());
    out.extend_from_slice(&(bytes.len() as u16).to_be_bytes());
    out.extend_from_slice(bytes);
    out
}

/// A STATUS message: code (1 is OK), subcode, error name, text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Status {
    pub code: u16,
    pub subcode: i64,
    pub error_name: String,
    pub text: String,
}

/// STATUS code of "OK".
pub const STATUS_OK: u16 = 1;

impl Status {
    pub fn decode(content: &[u8]) -> Result<Status, CodecError> {
        if content.len() < 30 {
            return Err(CodecError::content(
                "STATUS",
                "shorter than its 30-byte header",
            ));
        }
        let text = &content[30..];
        let end = text.iter().position(|&b| b == 0).unwrap_or(text.len());
        let name = &content[10..30];
        let name_end = name.iter().position(|&b| b == 0).unwrap_or(name.len());
        Ok(Status {
            code: be_u16(&content[0..2]),
            subcode: be_u64(&content[2..10]) as i64,
            error_name: String::from_utf8_lossy(&name[..name_end]).into_owned(),
            text: String::from_utf8_lossy(&text[..end]).into_owned(),
        })
    }

    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(31 + self.text.len());
        out.extend_from_slice(&self.code.to_be_bytes());
        out.extend_from_slice(&self.subcode.to_be_bytes());
        let mut name = [0u8; 20];
        let n = self.error_name.len().min(19);
        name[..n].copy_from_slice(&self.error_name.as_bytes()[..n]);
        out.extend_from_slice(&name);
        out.extend_from_slice(self.text.as_bytes());
        out.push(0);
        out
    }
}

/// The content bytes of a POLYDATA message holding a triangle mesh (points as f32, one polygon per
/// triangle, no attributes). `None` when the mesh is too large for the u32 counts.
pub fn encode_polydata(vertices: &[DVec3], triangles: &[[u32; 3]]) -> Option<Vec<u8>> {
    let npoints = u32::try_from(vertices.len()).ok()?;
    let npolygons = u32::try_from(triangles.len()).ok()?;
    let polygon_bytes = npolygons.checked_mul(16)?;
    let mut out =
        Vec::with_capacity(POLYDATA_HEADER_SIZE + 12 * vertices.len() + 16 * triangles.len());
    for v in [npoints, 0, 0, 0, 0, npolygons, polygon_bytes, 0, 0, 0] {
        out.extend_from_slice(&v.to_be_bytes());
    }
    for p in vertices {
        for c in [p.x, p.y, p.z] {
            out.extend_from_slice(&(c as f32).to_be_bytes());
        }
    }
    for t in triangles {
        for v in [3, t[0], t[1], t[2]] {
            out.extend_from_slice(&v.to_be_bytes());
        }
    }
    Some(out)
}

/// A POLYDATA message's points (f32 as sent) and polygons (point indices).
pub type PolyData = (Vec<[f32; 3]>, Vec<Vec<u32>>);

/// A POLYDATA message's points and polygons (vertices, lines and strips are skipped; attributes
/// are not read). Every polygon index is checked against the point count.
pub fn decode_polydata(content: &[u8]) -> Result<PolyData, CodecError> {
    let t = "POLYDATA";
    if content.len() < POLYDATA_HEADER_SIZE {
        return Err(CodecError::content(t, "shorter than its 40-byte header"));
    }
    let h: Vec<u64> = (0..10).map(|k| be_u32(&content[4 * k..]) as u64).collect();
    let points_bytes = h[0] * 12;
    let sections = [points_bytes, h[2], h[4], h[6], h[8]];
    let total = POLYDATA_HEADER_SIZE as u64 + sections.iter().sum::<u64>();
    if total > content.len() as u64 {
        return Err(CodecError::content(
            t,
            format!(
                "sections need {total} bytes, the body has {}",
                content.len()
            ),
        ));
    }
    let at_points = POLYDATA_HEADER_SIZE;
    let points: Vec<[f32; 3]> = content[at_points..at_points + points_bytes as usize]
        .chunks_exact(12)
        .map(|c| [be_f32(c), be_f32(&c[4..]), be_f32(&c[8..])])
        .collect();
    let at_polygons = at_points + (points_bytes + h[2] + h[4]) as usize;
    let words: Vec<u32> = content[at_polygons..at_polygons + h[6] as usize]
        .chunks_exact(4)
        .map(be_u32)
        .collect();
    let mut polygons = Vec::new();
    let mut k = 0;
    while k < words.len() {
        let n = words[k] as usize;
        let cell = words.get(k + 1..k + 1 + n).ok_or_else(|| {
            CodecError::content(
                t,
                format!("polygon {} runs past its section", polygons.len()),
            )
        })?;
        if cell.iter().any(|&i| i as u64 >= h[0]) {
            return Err(CodecError::content(
                t,
                format!("polygon {} indexes past the points", polygons.len()),
            ));
        }
        polygons.push(cell.to_vec());
        k += 1 + n;
    }
    if polygons.len() as u64 != h[5] {
        return Err(CodecError::content(
            t,
            format!(
                "{} polygons in the section, the header says {}",
                polygons.len(),
                h[5]
            ),
        ));
    }
    Ok((points, polygons))
}

/// A whole message: header (CRC of the body filled in) then body. With `version >= 2` the body gets
/// the extended header and `metadata` (a version 1 message drops the metadata, as the spec has none).
pub fn encode_message(
    version: u16,
    type_name: &str,
    device_name: &str,
    timestamp_s: f64,
    content: &[u8],
    metadata: &[(String, String)],
    message_id: u32,
) -> Vec<u8> {
    let mut body = Vec::with_capacity(content.len() + 64);
    if version >= 2 {
        let mut meta_header = Vec::new();
        let mut meta_body = Vec::new();
        meta_header
            .extend_from_slice(&(metadata.len().min(u16::MAX as usize) as u16).to_be_bytes());
        for (key, value) in metadata.iter().take(u16::MAX as usize) {
            let key = &key.as_bytes()[..key.len().min(u16::MAX as usize)];
            meta_header.extend_from_slice(&(key.len() as u16).to_be_bytes());
            meta_header.extend_from_slice(&3u16.to_be_bytes());
            meta_header.extend_from_slice(&(value.len() as u32).to_be_bytes());
            meta_body.extend_from_slice(key);
            meta_body.extend_from_slice(value.as_bytes());
        }
        body.extend_from_slice(&(EXTENDED_HEADER_SIZE as u16).to_be_bytes());
        body.extend_from_slice(&(meta_header.len() as u16).to_be_bytes());
        body.extend_from_slice(&(meta_body.len() as u32).to_be_bytes());
        body.extend_from_slice(&message_id.to_be_bytes());
        body.extend_from_slice(content);
        body.extend_from_slice(&meta_header);
        body.extend_from_slice(&meta_body);
    } else {
        body.extend_from_slice(content);
    }
    let mut out = Vec::with_capacity(HEADER_SIZE + body.len());
    out.extend_from_slice(&version.to_be_bytes());
    out.extend_from_slice(&padded::<12>(type_name));
    out.extend_from_slice(&padded::<20>(device_name));
    out.extend_from_slice(&timestamp_bits(timestamp_s).to_be_bytes());
    out.extend_from_slice(&(body.len() as u64).to_be_bytes());
    out.extend_from_slice(&crc64(&body).to_be_bytes());
    out.extend_from_slice(&body);
    out
}

/// A name cut to N - 1 bytes (so it stays NUL-terminated) and padded with NULs.
fn padded<const N: usize>(name: &str) -> [u8; N] {
    let mut field = [0u8; N];
    let bytes: Vec<u8> = name
        .bytes()
        .filter(|b| (0x20..0x7f).contains(b))
        .take(N - 1)
        .collect();
    field[..bytes.len()].copy_from_slice(&bytes);
    field
}

/// Seconds -> the header's 32.32 fixed-point timestamp (negative or non-finite -> 0).
pub fn timestamp_bits(seconds: f64) -> u64 {
    if !(seconds.is_finite() && seconds >= 0.0) {
        return 0;
    }
    let whole = seconds.floor().min(u32::MAX as f64);
    let frac = ((seconds - whole) * 4_294_967_296.0)
        .floor()
        .min(u32::MAX as f64);
    ((whole as u64) << 32) | frac as u64
}

/// A decoded message body.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    Image(Image),
    Transform(DMat4),
    String(String),
    Status(Status),
    /// Points and polygons (what the tests read back).
    PolyData(Vec<[f32; 3]>, Vec<Vec<u32>>),
    /// A type this client does not use (GET_*, STT_*, POINT, ...): ignored.
    Other,
}

/// A message with its header and v2/v3 metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    pub header: Header,
    pub metadata: Vec<(String, String)>,
    pub message: Message,
}

impl Decoded {
    /// A metadata value by key (case-insensitive).
    pub fn metadata_value(&self, key: &str) -> Option<&str> {
        self.metadata
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(key))
            .map(|(_, v)| v.as_str())
    }
}

/// Decodes a CRC-checked message's body by its type.
pub fn decode(raw: &RawMessage) -> Result<Decoded, CodecError> {
    let split = split_body(&raw.header, &raw.body)?;
    let message = match raw.header.type_name.as_str() {
        "IMAGE" => Message::Image(Image::decode(split.content)?),
        "TRANSFORM" => Message::Transform(decode_transform(split.content)?),
        "STRING" => Message::String(decode_string(split.content)?),
        "STATUS" => Message::Status(Status::decode(split.content)?),
        "POLYDATA" => {
            let (points, polygons) = decode_polydata(split.content)?;
            Message::PolyData(points, polygons)
        }
        _ => Message::Other,
    };
    Ok(Decoded {
        header: raw.header.clone(),
        metadata: split.metadata,
        message,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn frame_matrix() -> DMat4 {
        let r = glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -0.2, 1.1);
        DMat4::from_scale_rotation_translation(
            DVec3::new(0.2, 0.2, 1.0),
            r,
            DVec3::new(10.0, -5.0, 3.0),
        )
    }

    fn read(bytes: &[u8]) -> Result<Decoded, CodecError> {
        let raw = read_message(&mut &bytes[..], &Limits::default())?;
        decode(&raw)
    }

    #[test]
    fn image_round_trips_in_every_version_with_metadata() {
        let pixels: Vec<u8> = (0..12 * 5).map(|i| (i * 7) as u8).collect();
        let image = Image::from_u8_frame(12, 5, pixels.clone(), &frame_matrix());
        let meta = vec![("TransformStatus".to_string(), "OK".to_string())];
        for version in 1..=3 {
            let bytes = encode_message(
                version,
                "IMAGE",
                "Image_Reference",
                12.25,
                &image.encode(),
                &meta,
                7,
            );
            let got = read(&bytes).unwrap();
            assert_eq!(got.header.version, version);
            assert_eq!(got.header.device_name, "Image_Reference");
            assert_eq!(got.header.timestamp_s(), 12.25);
            assert_eq!(
                got.metadata_value("transformstatus"),
                (version > 1).then_some("OK")
            );
            let Message::Image(back) = got.message else {
                panic!("not an image")
            };
            assert_eq!(back.pixels, pixels);
            // The centre travels as f32: the placement comes back within f32 rounding.
            let (a, b) = (back.ijk_to_world(), frame_matrix());
            for (x, y) in a.to_cols_array().iter().zip(b.to_cols_array()) {
                assert!((x - y).abs() < 1e-5, "{a} vs {b}");
            }
        }
    }

    /// The pixel placement: pixel 0 at the origin, the centre pixel at the sent centre.
    #[test]
    fn image_centre_is_the_middle_pixel() {
        let image = Image {
            components: 1,
            scalar_type: SCALAR_UINT8,
            big_endian: false,
            coordinate: 1,
            size: [3, 5, 1],
            axes_mm: [[0.5, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, 0.0, 1.0]],
            centre_mm: [1.0, 2.0, 3.0],
            pixels: vec![0; 15],
        };
        let m = image.ijk_to_world();
        assert_eq!(
            m.transform_point3(DVec3::new(1.0, 2.0, 0.0)),
            DVec3::new(1.0, 2.0, 3.0)
        );
        assert_eq!(m.transform_point3(DVec3::ZERO), DVec3::new(0.5, 1.5, 3.0));
    }

    #[test]
    fn transform_string_status_polydata_round_trip() {
        let m = frame_matrix();
        let got = read(&encode_message(
            2,
            "TRANSFORM",
            "ProbeToReference",
            1.0,
            &encode_transform(&m),
            &[],
            0,
        ))
        .unwrap();
        let Message::Transform(back) = got.message else {
            panic!()
        };
        assert!(back.abs_diff_eq(m, 1e-6));
        let got = read(&encode_message(
            1,
            "STRING",
            "Note",
            0.0,
            &encode_string("héllo"),
            &[],
            0,
        ))
        .unwrap();
        assert_eq!(got.message, Message::String("héllo".into()));
        let status = Status {
            code: 13,
            subcode: -2,
            error_name: "Busy".into(),
            text: "later".into(),
        };
        let got = read(&encode_message(
            3,
            "STATUS",
            "S",
            0.0,
            &status.encode(),
            &[],
            0,
        ))
        .unwrap();
        assert_eq!(got.message, Message::Status(status));
        let vertices = [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z];
        let triangles = [[0, 1, 2], [0, 2, 3]];
        let content = encode_polydata(&vertices, &triangles).unwrap();
        let got = read(&encode_message(
            2,
            "POLYDATA",
            "EchosurfSurface",
            0.0,
            &content,
            &[],
            0,
        ))
        .unwrap();
        let Message::PolyData(points, polygons) = got.message else {
            panic!()
        };
        assert_eq!(points[1], [1.0, 0.0, 0.0]);
        assert_eq!(polygons, vec![vec![0, 1, 2], vec![0, 2, 3]]);
    }

    #[test]
    fn faults_are_errors_that_say_whether_the_stream_goes_on() {
        let image = Image::from_u8_frame(4, 4, vec![9; 16], &frame_matrix());
        let good = encode_message(1, "IMAGE", "Image", 0.0, &image.encode(), &[], 0);
        let mut bad_crc = good.clone();
        *bad_crc.last_mut().unwrap() ^= 1;
        let e = read(&bad_crc).unwrap_err();
        assert!(
            matches!(e, CodecError::Crc { .. }) && e.framing_intact(),
            "{e}"
        );
        let mut bad_version = good.clone();
        bad_version[1] = 9;
        assert!(matches!(
            read(&bad_version).unwrap_err(),
            CodecError::Header(_)
        ));
        let mut huge = good.clone();
        huge[42..50].copy_from_slice(&u64::MAX.to_be_bytes());
        let e = read(&huge).unwrap_err();
        assert!(
            matches!(e, CodecError::BodyTooLarge { .. }) && !e.framing_intact(),
            "{e}"
        );
        let e = read(&good[..good.len() - 3]).unwrap_err();
        assert!(matches!(e, CodecError::Io(_)), "{e}");
        // A body whose CRC is right but whose image is short of pixels.
        let short = encode_message(1, "IMAGE", "Image", 0.0, &image.encode()[..80], &[], 0);
        let e = read(&short).unwrap_err();
        assert!(
            matches!(e, CodecError::Content { .. }) && e.framing_intact(),
            "{e}"
        );
    }

    /// Random and mutated bytes: every outcome is a value (Ok or Err), never a panic, and a successful
    /// read never consumes more than the limit allows.
    #[test]
    fn fuzzed_bytes_never_panic() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(30);
        let image = Image::from_u8_frame(8, 6, (0..48).collect(), &frame_matrix());
        let meta = vec![("TransformStatus".to_string(), "INVALID".to_string())];
        let seeds = [
            encode_message(2, "IMAGE", "Image", 3.0, &image.encode(), &meta, 1),
            encode_message(
                1,
                "TRANSFORM",
                "T",
                3.0,
                &encode_transform(&frame_matrix()),
                &[],
                0,
            ),
            encode_message(
                3,
                "POLYDATA",
                "P",
                0.0,
                &encode_polydata(&[DVec3::ZERO; 3], &[[0, 1, 2]]).unwrap(),
                &meta,
                0,
            ),
            encode_message(
                2,
                "STATUS",
                "S",
                0.0,
                &Status {
                    code: 1,
                    subcode: 0,
                    error_name: String::new(),
                    text: "x".into(),
                }
                .encode(),
                &[],
                0,
            ),
        ];
        let limits = Limits {
            max_body_bytes: 4096,
        };
        let mut decoded = 0;
        for case in 0..20_000 {
            let mut bytes = seeds[case % seeds.len()].clone();
            match case % 3 {
                0 => {
                    for _ in 0..rng.random_range(1..8) {
                        let i = rng.random_range(0..bytes.len());
                        bytes[i] = rng.random();
                    }
                }
                1 => bytes.truncate(rng.random_range(0..bytes.len())),
                _ => {
                    let n = rng.random_range(0..200);
                    bytes = (0..n).map(|_| rng.random()).collect();
                }
            }
            // Mutations that keep the CRC right exercise the body parsers, not only the CRC check.
            if bytes.len() >= HEADER_SIZE && rng.random_bool(0.5) {
                let crc = crc64(&bytes[HEADER_SIZE..]);
                bytes[50..58].copy_from_slice(&crc.to_be_bytes());
            }
            if let Ok(raw) = read_message(&mut &bytes[..], &limits) {
                assert!(raw.body.len() as u64 <= limits.max_body_bytes);
                if decode(&raw).is_ok() {
                    decoded += 1;
                }
            }
        }
        assert!(
            decoded > 0,
            "no mutated message decoded: the mutations never reached the body parsers"
        );
    }
}
