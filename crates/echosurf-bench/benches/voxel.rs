//! Voxel reconstruction of the real spine sweep (21 frames of 820x616 at 0.5 mm) as PLUS does it:
//! nearest-neighbour and trilinear splatting, with and without STICK hole filling.

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::io::{self, ReferenceChoice};
use echosurf::progress::NoProgress;
use echosurf::voxel::{HoleFilling, Interpolation, options_from_config_xml, reconstruct_volume};

use echosurf_testkit::real_data;
use real_data::real;

fn bench_reconstruct(c: &mut Criterion) {
    let seq_path = real("SpinePhantomFreehand.igs.mha");
    let cfg_path = real("PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml");
    let seq = io::read_sequence(&seq_path).expect("read sequence");
    let cal = io::read_calibration(&cfg_path).expect("read calibration");
    let poses =
        io::resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, &seq_path).expect("poses");
    let xml = std::fs::read_to_string(&cfg_path).expect("read config");
    let base = options_from_config_xml(&xml, &cfg_path).expect("options");
    let mut group = c.benchmark_group("voxel spine 0.5 mm");
    group.sample_size(10);
    for (name, interpolation, fill) in [
        ("nn mean", Interpolation::NearestNeighbor, false),
        ("nn mean stick", Interpolation::NearestNeighbor, true),
        ("linear mean", Interpolation::Linear, false),
        ("linear mean stick", Interpolation::Linear, true),
    ] {
        let mut options = base.clone();
        options.interpolation = interpolation;
        if !fill {
            options.hole_filling = HoleFilling::none();
        }
        group.bench_function(name, |b| {
            b.iter(|| reconstruct_volume(&seq, &poses, &options, &NoProgress).expect("volume"))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_reconstruct);
criterion_main!(benches);
