use super::*;

#[test]
fn the_weak_level_lies_between_the_background_and_the_iso_level() {
    let levels = IntensityLevels {
        background: 15.0,
        boundary: 90.0,
        strong_echo: 130.0,
        iso: 37.5,
    };
    let weak = WeakEchoes::default();
    // The demo's duck: 37.5 - 0.3 x (37.5 - 15) = 30.75.
    assert_eq!(weak.level_below(37.5, Some(levels)), Some(30.75));
    // Off, no background known, or a user level at or below the background: no extension.
    let off = WeakEchoes {
        level_fraction: 0.0,
        ..weak.clone()
    };
    assert_eq!(off.level_below(37.5, Some(levels)), None);
    assert_eq!(weak.level_below(37.5, None), None);
    assert_eq!(weak.level_below(15.0, Some(levels)), None);
    assert_eq!(weak.level_below(10.0, Some(levels)), None);
}
