//! Frames segmented per second at the PLUS scanner size, 820 x 616 (target >= 30 frames/s on 2 cores).

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use echosurf::progress::NoProgress;
use echosurf::segment::synthetic::synthetic_sweep;
use echosurf::segment::{InitialBand, SegmentOptions, segment_sequence};

fn bench_segment(c: &mut Criterion) {
    const FRAMES: usize = 20;
    let sweep = synthetic_sweep(820, 616, FRAMES, 0.08, 2.0, 1);
    let mut group = c.benchmark_group("segment");
    group.sample_size(10);
    group.throughput(Throughput::Elements(FRAMES as u64));
    let band = InitialBand::Polygon(vec![
        [0.0, 150.0],
        [819.0, 150.0],
        [819.0, 400.0],
        [0.0, 400.0],
    ]);
    // The defaults (the paper's edgels), `--chain-edgels --backward-pass` and `--wall-band` (the same
    // with the band in mm: every echoing wall in the share of pixels the segmentation issue asks for).
    let chained_backward = SegmentOptions {
        backward_pass: true,
        ..SegmentOptions::chained()
    };
    for (name, init, options) in [
        ("propagate_820x616", band.clone(), SegmentOptions::default()),
        (
            "auto_init_820x616",
            InitialBand::Auto,
            SegmentOptions::default(),
        ),
        ("chained_backward_820x616", band.clone(), chained_backward),
        ("wall_band_820x616", band, SegmentOptions::wall_band()),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| {
                segment_sequence(
                    &sweep.sequence,
                    &sweep.poses,
                    None,
                    &init,
                    &options,
                    &NoProgress,
                )
                .unwrap()
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench_segment);
criterion_main!(benches);
