//! Decoding an 8-bit grey PNG in tests (`#[path]`-included by the unit and CLI tests that check the
//! pictures echosurf writes pixel for pixel).

/// (width, height, pixels) of an 8-bit grey PNG; panics on anything else.
pub fn read_grey_png(path: &std::path::Path) -> (u32, u32, Vec<u8>) {
    let decoder = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0u8; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Grayscale);
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}
