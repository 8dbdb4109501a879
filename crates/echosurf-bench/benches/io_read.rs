//! Reading the real PLUS sweeps (zlib MetaImage and gzip NRRD) and resolving their poses.

use criterion::{Criterion, criterion_group, criterion_main};
use echosurf::io::{self, ReferenceChoice};

use echosurf_testkit::real_data;
use real_data::real;

fn bench_read(c: &mut Criterion) {
    let mut group = c.benchmark_group("io");
    group.sample_size(10);
    for name in [
        "SpinePhantomFreehand.igs.mha",
        "NwirePhantomFreehand.igs.nrrd",
    ] {
        let path = real(name);
        group.bench_function(format!("read {name}"), |b| {
            b.iter(|| io::read_sequence(&path).expect("read"))
        });
    }
    let seq_path = real("SpinePhantomFreehand.igs.mha");
    let seq = io::read_sequence(&seq_path).expect("read");
    let cal = io::read_calibration(&real(
        "PlusDeviceSet_VolumeReconstructionOnly_SpinePhantom_NN_MEAN.xml",
    ))
    .expect("calibration");
    group.bench_function("resolve_poses spine", |b| {
        b.iter(|| io::resolve_poses(&seq, Some(&cal), ReferenceChoice::Auto, &seq_path).unwrap())
    });
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("spine.mha");
    group.bench_function("write spine zlib", |b| {
        b.iter(|| io::write_sequence(&out, &seq, true).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_read);
criterion_main!(benches);
