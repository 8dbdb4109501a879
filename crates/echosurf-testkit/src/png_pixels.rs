//! Decoding the 8-bit PNGs echosurf writes, for the tests that check its pictures pixel by pixel.

/// (width, height, pixels) of an 8-bit PNG of colour type `colour`; panics on anything else.
pub fn read_png(path: &std::path::Path, colour: png::ColorType) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, colour);
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// An 8-bit grey PNG.
pub fn read_grey_png(path: &std::path::Path) -> (u32, u32, Vec<u8>) {
    read_png(path, png::ColorType::Grayscale)
}

/// An 8-bit RGB PNG.
pub fn read_rgb_png(path: &std::path::Path) -> (u32, u32, Vec<u8>) {
    read_png(path, png::ColorType::Rgb)
}
