//! echosurf's benchmark harness (`echosurf bench`): the direct RBF route against the voxel route on the
//! same data, scored against ground truth ([`scoring`], [`patches`]), and the fit's cost against the
//! number of samples ([`fit_scaling`]); results as markdown and SVG ([`report`], [`svg`]). Cases come
//! from the simulator (`echosurf-sim`) or a user's sweep with its truth ([`case`]). The criterion benches
//! live in `benches/`, measurement tools in `examples/`.

pub mod band_pixels;
pub mod case;
pub mod fit_scaling;
pub mod patches;
pub mod report;
pub mod run;
pub mod scoring;
pub mod svg;

pub use band_pixels::{
    BAND_DILATION_PX, BAND_SMOOTHING_SIGMA_PX, BAND_THRESHOLD_GREY, all_band_pixels, band_pixels,
    random_subset, simulated_band_pixels, sweep_band_pixels,
};
pub use case::{
    BenchCase, BenchOptions, NoiseLevel, simulated_case, simulation_options, user_case,
};
pub use fit_scaling::{ScalingRow, ScalingSamples, bench_fit_scaling, fit_sizes};
pub use patches::{
    MIN_PATCH_AREA_MM2, PatchCoverage, PatchDetail, largest_piece_area_share, patch_count,
    patch_coverage, patch_details, patches_of,
};
pub use report::{accuracy_vs_time_plot, fit_scaling_plot, markdown_table};
pub use run::{ROUTES, RouteResult, run_case};
pub use scoring::{
    FacingSide, PROBE_FACING_DEG, STRONG_ECHO_DEG, SweptFacingScore, SweptFacingTruth,
    facing_within, median_spacing, swept_beam_cosines, swept_beam_facing_mask,
};
