//! Reading a command's tracked sequence and calibration with the checks that need both, or that warn
//! rather than refuse: a clip rectangle that misses every pixel of the frames is refused before any
//! work, timestamps that go backwards are reported.

use std::path::Path;

use echosurf::io::{self, Calibration, TrackedSequence};

/// Reads a tracked sequence, warning on stderr when its timestamps go backwards (frames are still
/// used in file order, as PLUS does).
pub fn read_sequence(path: &Path) -> anyhow::Result<TrackedSequence> {
    let sequence = io::read_sequence(path)?;
    if let Some(warning) = backwards_timestamps(&sequence) {
        eprintln!("warning: {}: {warning}", path.display());
    }
    Ok(sequence)
}

/// Reads a calibration and refuses one whose clip rectangle leaves no pixel of `sequence`'s frames.
pub fn read_calibration_for(
    config: &Path,
    sequence: &TrackedSequence,
    sequence_path: &Path,
) -> anyhow::Result<Calibration> {
    let calibration = io::read_calibration(config)?;
    check_clip(&calibration, sequence, config, sequence_path)?;
    Ok(calibration)
}

/// Refuses a clip rectangle outside the frames (the library's check).
pub fn check_clip(
    calibration: &Calibration,
    sequence: &TrackedSequence,
    config: &Path,
    sequence_path: &Path,
) -> anyhow::Result<()> {
    Ok(io::check_clip_fits(
        calibration,
        sequence,
        config,
        sequence_path,
    )?)
}

/// How often timestamps go backwards and where first, if they do.
pub fn backwards_timestamps(sequence: &TrackedSequence) -> Option<String> {
    let mut previous: Option<(usize, f64)> = None;
    let mut first = None;
    let mut count = 0usize;
    for (index, frame) in sequence.frames.iter().enumerate() {
        let Some(t) = frame.timestamp_s else { continue };
        if let Some((_, before)) = previous
            && t < before
        {
            count += 1;
            first.get_or_insert((index, t, before));
        }
        previous = Some((index, t));
    }
    let (index, t, before) = first?;
    Some(format!(
        "timestamps go backwards {count} time(s), first at frame {index} ({t} s after {before} s); \
         frames are used in file order"
    ))
}

#[cfg(test)]
mod tests {
    use super::backwards_timestamps;
    use echosurf::io::{PixelData, TrackedFrame, TrackedSequence};

    #[test]
    fn backwards_timestamps_are_counted_from_the_first() {
        let frame = |t: f64| TrackedFrame {
            timestamp_s: Some(t),
            ..TrackedFrame::default()
        };
        let mut sequence = TrackedSequence {
            width: 1,
            height: 1,
            channels: 1,
            orientation: "MF".into(),
            frames: [0.0, 0.1, 0.2].map(frame).to_vec(),
            pixels: PixelData::U8(vec![0; 3]),
            header: Default::default(),
        };
        assert_eq!(backwards_timestamps(&sequence), None);
        sequence.frames = [0.0, 0.3, 0.2, 0.4, 0.1].map(frame).to_vec();
        let warning = backwards_timestamps(&sequence).unwrap();
        assert!(
            warning.starts_with("timestamps go backwards 2 time(s), first at frame 2"),
            "{warning}"
        );
    }
}
