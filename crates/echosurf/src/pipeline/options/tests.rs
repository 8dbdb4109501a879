use super::*;
use crate::pipeline::MIN_PIECE_SHARE_OF_LARGEST;
use crate::rbf::SolverChoice;

/// The first error of `config` after `change`.
fn refused(change: impl FnOnce(&mut ExtractConfig)) -> OptionError {
    let mut config = ExtractConfig::default();
    change(&mut config);
    config
        .validate()
        .expect_err("an out-of-range value was accepted")
}

#[test]
fn the_defaults_validate_and_are_the_pipelines_defaults() {
    let config = ExtractConfig::default();
    config.validate().unwrap();
    let options = config.to_extract_options(InitialBand::Auto);
    // The values `extract` has always used without options (the paper's and the measured ones).
    assert!(matches!(options.iso, IsoLevels::Auto));
    assert!(matches!(options.method, Method::Rbf));
    assert_eq!(options.sheet, Sheet::Auto);
    assert_eq!((options.seed, options.fit.seed), (1, 1));
    assert_eq!(options.max_samples, 100_000);
    assert_eq!(options.fit.smoothing, 2.0);
    assert_eq!(options.fit.accuracy, 2.0);
    assert_eq!(options.surface.resolution_mm, 0.5);
    assert_eq!(options.sample_bin_mm, 0.4);
    assert_eq!(options.echo_margin_mm, Some(1.0));
    assert_eq!(options.trust_distance_mm, None);
    assert_eq!(options.min_component_area_mm2, None);
    assert_eq!(
        options.min_piece_share_of_largest(),
        MIN_PIECE_SHARE_OF_LARGEST
    );
    assert_eq!(MIN_PIECE_SHARE_OF_LARGEST, 0.005);
    assert_eq!(options.min_echo_frames, 3);
    assert_eq!(options.max_echo_distance_mm, 1.5);
    assert_eq!(options.bridge_gap_mm, 2.0);
    assert_eq!(options.trim_rim_rings, 0);
    assert_eq!(options.echo_sheet, SheetOptions::default());
    assert_eq!(options.weak_echoes, WeakEchoes::default());
    assert_eq!(options.segment, SegmentOptions::default());
    assert_eq!(
        options.memory_budget_bytes,
        Some(crate::budget::default_memory_budget_bytes())
    );
}

#[test]
fn every_knob_survives_a_round_trip_through_serde() {
    let mut config = ExtractConfig::default();
    config.user.iso = IsoLevels::Levels(vec![40.0, 60.5]);
    config.user.sheet = Sheet::EchoRidge;
    config.user.method = MethodChoice::Voxel;
    config.tuning.world = ReferenceChoice::Tracker;
    config.tuning.memory_budget_mb = Some(512.0);
    config.tuning.fit.solver = SolverChoice::PartitionOfUnity;
    config.tuning.cleanup.min_component_area_mm2 = Some(0.0);
    config.tuning.segment.backward_pass = true;
    let text = serde_json::to_string(&config).unwrap();
    let back: ExtractConfig = serde_json::from_str(&text).unwrap();
    assert_eq!(back, config);
    // Missing keys take the defaults; unknown keys are refused, naming the key.
    let partial: ExtractConfig =
        serde_json::from_str(r#"{"user": {"seed": 7}, "tuning": {"ridge": {"reach_mm": 1.0}}}"#)
            .unwrap();
    assert_eq!(partial.user.seed, 7);
    assert_eq!(partial.tuning.ridge.reach_mm, 1.0);
    assert_eq!(
        partial.tuning.ridge.smoothing_mm,
        SheetOptions::default().smoothing_mm
    );
    assert_eq!(partial.tuning.cleanup, CleanupTuning::default());
    let unknown = serde_json::from_str::<ExtractConfig>(r#"{"tuning": {"ridge": {"colour": 1}}}"#)
        .unwrap_err()
        .to_string();
    assert!(unknown.contains("colour"), "{unknown}");
    let word = serde_json::from_str::<ExtractConfig>(r#"{"user": {"sheet": "flat"}}"#)
        .unwrap_err()
        .to_string();
    assert!(word.contains("expected one of auto, iso, ridge"), "{word}");
}

#[test]
fn a_smallest_piece_given_replaces_the_share_of_the_largest() {
    let mut config = ExtractConfig::default();
    config.tuning.cleanup.min_component_area_mm2 = Some(3.0);
    let options = config.to_extract_options(InitialBand::Auto);
    assert_eq!(options.min_component_area_mm2, Some(3.0));
    assert_eq!(options.min_component_area_for(Sheet::EchoRidge), 3.0);
    assert_eq!(options.min_piece_share_of_largest(), 0.0);
}

#[test]
fn cleanup_off_keeps_the_surface_as_drawn() {
    let mut config = ExtractConfig::default();
    config.user.cleanup = false;
    let options = config.to_extract_options(InitialBand::Auto);
    assert_eq!(options.max_echo_distance_mm, 0.0);
    assert_eq!(options.min_component_area_mm2, Some(0.0));
    // Cleanup off keeps every piece, however small beside the largest.
    assert_eq!(options.min_piece_share_of_largest(), 0.0);
    assert_eq!(options.min_echo_frames, 0);
    assert_eq!(options.bridge_gap_mm, 0.0);
    assert_eq!(options.trim_rim_rings, 0);
}

#[test]
fn the_segment_threshold_is_a_fraction() {
    let e = refused(|c| c.tuning.segment.threshold = 1.5);
    assert_eq!(
        e.to_string(),
        "tuning.segment.threshold must be in (0, 1], got 1.5"
    );
    assert_eq!(
        refused(|c| c.tuning.segment.threshold = 0.0).field,
        "tuning.segment.threshold"
    );
    // The segmentation's own checks are named under its section.
    assert_eq!(
        refused(|c| c.tuning.segment.edgel_fraction = 0.0).field,
        "tuning.segment"
    );
}

#[test]
fn each_range_check_names_its_field() {
    type Change = fn(&mut ExtractConfig);
    let cases: &[(&str, Change)] = &[
        ("user.iso", |c| {
            c.user.iso = IsoLevels::Levels(vec![40.0, 40.0])
        }),
        ("user.iso", |c| {
            c.user.iso = IsoLevels::Levels(vec![f64::NAN])
        }),
        ("user.iso", |c| c.user.iso = IsoLevels::Levels(vec![])),
        ("user.smoothing_mm", |c| c.user.smoothing_mm = -1.0),
        ("user.resolution_mm", |c| c.user.resolution_mm = 0.0),
        ("user.resolution_mm", |c| c.user.resolution_mm = f64::NAN),
        ("user.max_samples", |c| c.user.max_samples = 0),
        ("tuning.memory_budget_mb", |c| {
            c.tuning.memory_budget_mb = Some(0.0)
        }),
        ("tuning.memory_budget_mb", |c| {
            c.tuning.memory_budget_mb = Some(-5.0)
        }),
        ("tuning.trust_distance_mm", |c| {
            c.tuning.trust_distance_mm = Some(0.0)
        }),
        ("tuning.sampling.bin_mm", |c| {
            c.tuning.sampling.bin_mm = -0.1
        }),
        ("tuning.sampling.echo_margin_mm", |c| {
            c.tuning.sampling.echo_margin_mm = -1.0
        }),
        ("tuning.fit.accuracy_grey", |c| c.tuning.fit.accuracy = 0.0),
        ("tuning.fit.eval_accuracy", |c| {
            c.tuning.fit.eval_accuracy = 1.0
        }),
        ("tuning.fit.pu_leaf_points", |c| {
            c.tuning.fit.pu_leaf_points = 0
        }),
        ("tuning.surface.cluster_cell_factor", |c| {
            c.tuning.surface.cluster_cell_factor = 0.0
        }),
        ("tuning.ridge.smoothing_mm", |c| {
            c.tuning.ridge.smoothing_mm = 0.0
        }),
        ("tuning.ridge.reach_mm", |c| c.tuning.ridge.reach_mm = -1.0),
        ("tuning.weak_echoes.reach_mm", |c| {
            c.tuning.weak_echoes.reach_mm = f64::INFINITY
        }),
        ("tuning.ridge.bridge_mm", |c| {
            c.tuning.ridge.bridge_mm = -0.5
        }),
        ("tuning.weak_echoes.level_fraction", |c| {
            c.tuning.weak_echoes.level_fraction = 1.0
        }),
        ("tuning.weak_echoes.level_fraction", |c| {
            c.tuning.weak_echoes.level_fraction = -0.1
        }),
        ("tuning.image_crests.link_mm", |c| {
            c.tuning.image_crests.link_mm = 0.0
        }),
        ("tuning.image_crests.normal_radius_mm", |c| {
            c.tuning.image_crests.normal_radius_mm = f64::NAN
        }),
        ("tuning.image_crests.crest", |c| {
            c.tuning.image_crests.crest.min_contrast_ratio = 0.9
        }),
        ("tuning.cleanup.max_echo_distance_mm", |c| {
            c.tuning.cleanup.max_echo_distance_mm = -1.0
        }),
        ("tuning.cleanup.min_component_area_mm2", |c| {
            c.tuning.cleanup.min_component_area_mm2 = Some(-2.0)
        }),
        ("tuning.cleanup.bridge_gap_mm", |c| {
            c.tuning.cleanup.bridge_gap_mm = f64::NAN
        }),
        ("tuning.voxel.spacing_mm", |c| {
            c.tuning.voxel.spacing_mm = Some(0.0)
        }),
        ("tuning.voxel.smoothing_sigma_mm", |c| {
            c.tuning.voxel.smoothing_sigma_mm = -1.0
        }),
    ];
    for (field, change) in cases {
        let e = refused(change);
        assert_eq!(&e.field, field, "{e}");
        assert!(e.to_string().starts_with(field), "{e}");
    }
    // Zero is a valid "off" for the distances and thinning margins.
    let mut config = ExtractConfig::default();
    config.tuning.ridge.bridge_mm = 0.0;
    config.tuning.weak_echoes.level_fraction = 0.0;
    config.tuning.sampling.echo_margin_mm = 0.0;
    config.tuning.cleanup.max_echo_distance_mm = 0.0;
    config.tuning.voxel.smoothing_sigma_mm = 0.0;
    config.validate().unwrap();
    assert_eq!(
        config.to_extract_options(InitialBand::Auto).echo_margin_mm,
        None
    );
}

#[test]
fn the_tuning_sections_are_the_stage_options_and_the_user_tier_knobs_are_not_in_them() {
    // `[tuning.fit]` is `rbf::FitOptions`: a value set there reaches the fit unchanged.
    let parsed: ExtractConfig = serde_json::from_str(
        r#"{"tuning": {"fit": {"accuracy_grey": 0.5, "solver": "pu"},
            "weak_echoes": {"reach_mm": 2.0}, "voxel": {"spacing_mm": "auto"}}}"#,
    )
    .unwrap();
    let options = parsed.to_extract_options(InitialBand::Auto);
    assert_eq!(options.fit.accuracy, 0.5);
    assert_eq!(options.fit.solver, SolverChoice::PartitionOfUnity);
    assert_eq!(options.weak_echoes.reach_mm, 2.0);
    // The smoothing, seed and resolution are the user tier's: their stage fields are not keys.
    for (section, key) in [
        ("fit", "smoothing"),
        ("fit", "seed"),
        ("surface", "resolution_mm"),
        ("surface", "trust_distance_mm"),
    ] {
        let text = format!(r#"{{"tuning": {{"{section}": {{"{key}": 1.0}}}}}}"#);
        let err = serde_json::from_str::<ExtractConfig>(&text)
            .unwrap_err()
            .to_string();
        assert!(err.contains(&format!("unknown field `{key}`")), "{err}");
    }
    let mut config = ExtractConfig::default();
    config.user.smoothing_mm = 3.0;
    config.user.seed = 9;
    config.user.resolution_mm = 0.75;
    let options = config.to_extract_options(InitialBand::Auto);
    assert_eq!(
        (options.fit.smoothing, options.fit.seed),
        (3.0, 9),
        "the user tier sets the fit"
    );
    assert_eq!(options.surface.resolution_mm, 0.75);
}
