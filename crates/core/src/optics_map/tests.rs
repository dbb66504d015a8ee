//! The optics map against hand-computed values and SciPy's PCHIP.

use super::*;

fn range(lo: f32, hi: f32) -> PowerRange {
    PowerRange::new(Diopters(lo), Diopters(hi)).unwrap()
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol
}

/// Display 5 cm from the tunable lens, an 18 D eyepiece at the lens, the pupil 2 cm behind it.
fn eyepiece() -> ThinLensLayout {
    ThinLensLayout::new(0.05, 0.02, 18.0).unwrap()
}

/// The map of `layout` and `rx` for a lens driven within -2..2 D.
fn layout_map(layout: ThinLensLayout, rx: Prescription) -> OpticsMap {
    OpticsMap::new(Some(layout), None, rx, range(-2.0, 2.0)).unwrap()
}

/// `layout`'s demand every 0.5 D over -2..2 D, as a calibration would measure it.
fn sampled(layout: &ThinLensLayout) -> Vec<(f64, f64)> {
    (0..=8)
        .map(|k| {
            let c = -2.0 + 0.5 * f64::from(k);
            (c, layout.demand_at(c))
        })
        .collect()
}

#[test]
fn identity_when_nothing_is_configured() {
    let m = OpticsMap::new(None, None, Prescription::default(), range(-1.0, 4.0)).unwrap();
    assert!(m.is_identity());
    assert_eq!(m, OpticsMap::identity(range(-1.0, 4.0)));
    for f in [-1.0f32, 0.0, 0.37, 2.2, 4.0] {
        assert_eq!(m.command_for(Diopters(f)), Diopters(f));
        assert_eq!(m.focus_of(Diopters(f)), Diopters(f));
    }
    // Commands stay inside the lens range.
    assert_eq!(m.command_for(Diopters(9.0)), Diopters(4.0));
    assert_eq!(m.magnification(Diopters(1.0)), None);
    assert_eq!(m.source_name(), "identity");
    assert!(m.describe().starts_with("identity"), "{}", m.describe());
}

#[test]
fn lens_at_the_eye_is_linear() {
    // s = 0: A = 1/d - F - t = 20 - 18 - t = 2 - t.
    let l = ThinLensLayout::new(0.05, 0.0, 18.0).unwrap();
    let m = OpticsMap::new(Some(l), None, Prescription::default(), range(-2.0, 4.0)).unwrap();
    for (t, a) in [
        (-2.0f32, 4.0f32),
        (-1.0, 3.0),
        (0.0, 2.0),
        (0.5, 1.5),
        (2.0, 0.0),
        (4.0, -2.0),
    ] {
        assert!(
            close(m.focus_of(Diopters(t)).0.into(), a.into(), 1e-5),
            "{t}"
        );
        assert!(
            close(m.command_for(Diopters(a)).0.into(), t.into(), 1e-5),
            "{a}"
        );
        // A lens at the pupil does not change the image's angular size.
        assert!(close(
            m.magnification(Diopters(t)).unwrap().into(),
            1.0,
            1e-6
        ));
    }
    // No fixed lens, display 1 m away: the bare display is 1 D; +1 D of lens puts it at infinity.
    let bare = ThinLensLayout::new(1.0, 0.0, 0.0).unwrap();
    assert!(close(bare.demand_at(0.0), 1.0, 1e-12));
    assert!(close(bare.demand_at(1.0), 0.0, 1e-12));
}

#[test]
fn lens_away_from_the_eye_follows_the_thin_lens_formula() {
    // By hand, d = 0.05, s = 0.02, F = 18: X = 20 - 18 - t, A = X / (1 + 0.02 X).
    //   t = 0: X = 2, A = 2 / 1.04 = 1.923077; t = 1: 1 / 1.02 = 0.980392;
    //   t = -2: 4 / 1.08 = 3.703704.
    // Inverse, A = 1: X = 1 / (1 - 0.02) = 1.020408, t = 2 - 1.020408 = 0.979592.
    let m = layout_map(eyepiece(), Prescription::default());
    for (t, a) in [(0.0f32, 1.923077f64), (1.0, 0.980392), (-2.0, 3.703704)] {
        assert!(close(m.focus_of(Diopters(t)).0.into(), a, 2e-6), "{t}");
        assert!(
            close(m.command_for(Diopters(a as f32)).0.into(), t.into(), 2e-5),
            "{a}"
        );
    }
    assert!(close(m.command_for(Diopters(1.0)).0.into(), 0.979592, 2e-6));
    // Not linear: equal steps of command give unequal steps of demand.
    let step = |t: f32| m.focus_of(Diopters(t)).0 - m.focus_of(Diopters(t + 1.0)).0;
    assert!((step(-2.0) - step(0.0)).abs() > 0.05);
    // Magnification by hand: (d + s) / (d + s - s d P), P = 18 + t:
    //   t = 0: 0.07 / 0.052 = 1.346154; t = 1: 0.07 / 0.051 = 1.372549.
    assert!(close(
        m.magnification(Diopters(0.0)).unwrap().into(),
        1.346154,
        1e-6
    ));
    assert!(close(
        m.magnification(Diopters(1.0)).unwrap().into(),
        1.372549,
        1e-6
    ));
    assert_eq!(m.source_name(), "layout");
}

#[test]
fn round_trips_hold_across_the_range() {
    let l = eyepiece();
    let table = CalibrationTable::new("t.csv", &sampled(&l)).unwrap();
    for m in [
        layout_map(l, Prescription::default()),
        OpticsMap::new(
            None,
            Some(table),
            Prescription::new(-1.5, 0.0, 0.012).unwrap(),
            range(-2.0, 2.0),
        )
        .unwrap(),
    ] {
        for k in 0..=40 {
            let c = Diopters(-2.0 + 0.1 * k as f32);
            let back = m.command_for(m.focus_of(c));
            assert!(
                (back.0 - c.0).abs() < 1e-4,
                "{}: {c} -> {back}",
                m.describe()
            );
        }
    }
}

#[test]
fn a_table_reproduces_the_layout_it_was_measured_on() {
    // A table sampled from the layout every 0.5 D agrees with the formula between the
    // points to within a few thousandths of a diopter.
    let l = eyepiece();
    let t = CalibrationTable::new("sampled", &sampled(&l)).unwrap();
    for k in 0..=80 {
        let c = -2.0 + 0.05 * f64::from(k);
        assert!(close(t.demand_at(c), l.demand_at(c), 2e-3), "{c}");
    }
}

#[test]
fn pchip_matches_scipy() {
    // SciPy 1.17.1, scipy.interpolate.PchipInterpolator(x, y)(q), for these points.
    let x = [-1.0, -0.5, 0.0, 0.7, 1.5, 2.0, 3.0, 4.0];
    let y = [3.1, 2.55, 2.2, 1.5, 0.9, 0.75, 0.2, -0.1];
    let t = CalibrationTable::new("falling", &x.into_iter().zip(y).collect::<Vec<_>>()).unwrap();
    for (q, want) in [
        (-0.8, 2.8538666666666663),
        (-0.25, 2.3724986515641855),
        (0.35, 1.853879630202214),
        (1.0, 1.2385621357907575),
        (1.75, 0.8225659843792081),
        (2.5, 0.47653574087862993),
        (3.9, -0.08091911764705882),
    ] {
        assert!(
            close(t.demand_at(q), want, 1e-12),
            "{q}: {}",
            t.demand_at(q)
        );
        assert!(close(t.command_for(want), q, 1e-9), "{q}");
    }
    // A rising table whose first end slope the shape rule sets to 0.
    let x = [0.0, 1.0, 2.0, 3.0, 4.0];
    let y = [0.0, 0.1, 1.5, 1.6, 3.0];
    let t = CalibrationTable::new("rising", &x.into_iter().zip(y).collect::<Vec<_>>()).unwrap();
    for (q, want) in [
        (0.5, 0.026666666666666672),
        (1.5, 0.8),
        (2.5, 1.5500000000000003),
        (3.5, 2.0670833333333336),
    ] {
        assert!(
            close(t.demand_at(q), want, 1e-12),
            "{q}: {}",
            t.demand_at(q)
        );
    }
    // Outside the table: its ends.
    assert_eq!(t.demand_at(-1.0), 0.0);
    assert_eq!(t.command_for(9.0), 4.0);
}

#[test]
fn tables_that_are_not_monotone_or_too_sparse_are_refused_naming_the_points() {
    let csv = "# a hand-made table\ncommand_d,demand_d,note\n0,2.0,a\n1,1.5,b\n2,1.6,c\n3,0.5,d\n";
    let e = CalibrationTable::parse_csv("left.csv", csv)
        .unwrap_err()
        .to_string();
    assert!(e.contains("left.csv") && e.contains("not monotonic"), "{e}");
    assert!(e.contains("(command 1 D, demand 1.5 D) (line 4)"), "{e}");
    assert!(e.contains("(command 2 D, demand 1.6 D) (line 5)"), "{e}");
    // Too few points.
    let e = CalibrationTable::parse_csv("f.csv", "command_d,demand_d\n0,1\n1,0\n2,-1\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 points") && e.contains("at least 4"), "{e}");
    // Dense enough points, but a gap inside the lens range.
    let t = CalibrationTable::parse_csv(
        "gap.csv",
        "command_d,demand_d\n-1,3\n-0.5,2.5\n0,2\n1.5,0.5\n2,0\n",
    )
    .unwrap();
    let e = OpticsMap::new(
        None,
        Some(t.clone()),
        Prescription::default(),
        range(-1.0, 2.0),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("gap.csv") && e.contains("too sparse"), "{e}");
    assert!(
        e.contains("(command 0 D, demand 2 D) and (command 1.5 D, demand 0.5 D)"),
        "{e}"
    );
    // Not covering the range.
    let e = OpticsMap::new(None, Some(t), Prescription::default(), range(-1.0, 3.0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("span -1..2 D") && e.contains("-1..3 D"), "{e}");
    // Malformed files name the line or the column.
    let e = CalibrationTable::parse_csv("x.csv", "command_d,demand\n0,1\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("no demand_d column"), "{e}");
    let e = CalibrationTable::parse_csv("x.csv", "command_d,demand_d\n0,1\n1,far\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("line 3") && e.contains("\"far\""), "{e}");
    let e = CalibrationTable::parse_csv("x.csv", "# only comments\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("no header"), "{e}");
    let e = CalibrationTable::new("x", &[(0.0, 1.0), (0.0, 2.0), (1.0, 3.0), (2.0, 4.0)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("appears twice"), "{e}");
}

#[test]
fn a_table_written_is_read_back_the_same() {
    let t = CalibrationTable::new("w", &[(0.0, 2.0), (0.5, 1.4), (1.0, 0.9), (1.5, 0.45)]).unwrap();
    let text = t.to_csv(
        &["dioptra lens calibration".into(), "lens serial X1".into()],
        &["temperature_c"],
        &[
            vec!["30.1".into()],
            vec!["30.2".into()],
            vec!["30.2".into()],
            vec!["30.3".into()],
        ],
    );
    assert!(text.starts_with("# dioptra lens calibration\n# lens serial X1\ncommand_d,demand_d,temperature_c\n0.0000,2.0000,30.1\n"), "{text}");
    let back = CalibrationTable::parse_csv("w", &text).unwrap();
    assert_eq!(
        back.points().collect::<Vec<_>>(),
        t.points().collect::<Vec<_>>()
    );
    assert_eq!(back.lines(), &[4, 5, 6, 7]);
}

#[test]
fn prescription_shifts_each_eye_and_zero_changes_nothing() {
    // At a 0 mm vertex distance the shift is exactly -R: a -1 D myope at 1.5 D is shown 2.5 D.
    let at_eye = Prescription::new(-1.0, 0.0, 0.0).unwrap();
    assert!(close(at_eye.presented(1.5), 2.5, 1e-12));
    assert!(close(at_eye.focus_of(2.5), 1.5, 1e-12));
    // At 12 mm, by hand: L = -1.5 / (1 - 0.018) = -1.527495; L' = -2.527495;
    // V = L' / (1 + 0.012 * 2.527495) = -2.453093; shown 2.453093 D.
    let spectacles = Prescription::new(-1.0, 0.0, 0.012).unwrap();
    assert!(close(spectacles.presented(1.5), 2.4530927549753705, 1e-12));
    assert!(close(spectacles.focus_of(2.4530927549753705), 1.5, 1e-12));
    // Per eye, through the identity optics: the left eye's -1 D and the right eye's +2 D.
    let r = range(-3.0, 6.0);
    let left = OpticsMap::new(None, None, at_eye, r).unwrap();
    let right = OpticsMap::new(None, None, Prescription::new(2.0, 0.0, 0.0).unwrap(), r).unwrap();
    let plain = OpticsMap::identity(r);
    for f in [0.0f32, 0.5, 1.5, 2.2] {
        assert!(close(
            left.command_for(Diopters(f)).0.into(),
            f64::from(f) + 1.0,
            1e-6
        ));
        assert!(close(
            right.command_for(Diopters(f)).0.into(),
            f64::from(f) - 2.0,
            1e-6
        ));
        assert!(close(
            left.focus_of(left.command_for(Diopters(f))).0.into(),
            f.into(),
            1e-5
        ));
        assert_eq!(plain.command_for(Diopters(f)), Diopters(f));
    }
    // Through a layout, the prescription moves the demand before the optics: the command
    // for focus f with Rx -1 (0 mm) is the layout's command for f + 1.
    let l = eyepiece();
    let with_rx = layout_map(l, at_eye);
    let without = layout_map(l, Prescription::default());
    for f in [0.5f32, 1.0, 2.0] {
        assert_eq!(
            with_rx.command_for(Diopters(f)),
            without.command_for(Diopters(f + 1.0))
        );
    }
    // 0 changes nothing, at any vertex distance.
    let zero = Prescription::new(0.0, 0.0, 0.012).unwrap();
    assert!(zero.is_none());
    assert_eq!(zero.presented(1.234), 1.234);
    let m = layout_map(l, zero);
    assert_eq!(m, without);
}

#[test]
fn cylinder_and_bad_values_are_refused_with_the_key() {
    let e = Prescription::new(-2.0, -0.75, 0.012).unwrap_err();
    assert!(
        matches!(
            e,
            OpticsError::Invalid {
                key: "prescription_cylinder_d",
                ..
            }
        ),
        "{e}"
    );
    let s = e.to_string();
    assert!(
        s.contains("spherical equivalent") && s.contains("-2.38 D"),
        "{s}"
    );
    for (r, key) in [
        (
            Prescription::new(f64::NAN, 0.0, 0.012),
            "prescription_sphere_d",
        ),
        (
            Prescription::new(-25.0, 0.0, 0.012),
            "prescription_sphere_d",
        ),
        (Prescription::new(-1.0, 0.0, 0.05), "prescription_vertex_mm"),
    ] {
        assert!(
            matches!(r, Err(OpticsError::Invalid { key: k, .. }) if k == key),
            "{r:?}"
        );
    }
    for (r, key) in [
        (ThinLensLayout::new(0.0, 0.01, 0.0), "display_distance_m"),
        (ThinLensLayout::new(0.05, -0.01, 0.0), "eye_relief_m"),
        (
            ThinLensLayout::new(0.05, 0.01, f64::INFINITY),
            "fixed_power_d",
        ),
    ] {
        assert!(
            matches!(r, Err(OpticsError::Invalid { key: k, .. }) if k == key),
            "{r:?}"
        );
    }
}

#[test]
fn a_layout_whose_image_reaches_the_eye_is_refused() {
    // d = 0.05, s = 0.05, F = 40: X = 20 - 40 - t = -20 - t; 1 + s X = 1 - 1 - 0.05 t = -0.05 t:
    // the pole is at t = 0, inside a -1..1 D range.
    let l = ThinLensLayout::new(0.05, 0.05, 40.0).unwrap();
    let e = OpticsMap::new(Some(l), None, Prescription::default(), range(-1.0, 1.0)).unwrap_err();
    assert!(
        matches!(e, OpticsError::Invalid { key: "layout", .. }),
        "{e}"
    );
}

#[test]
fn demands_out_of_reach_give_the_nearest_command_the_lens_has() {
    let m = layout_map(eyepiece(), Prescription::default());
    // Beyond 1/s = 50 D the formula has no answer; demand rises as power falls.
    assert_eq!(m.command_for(Diopters(80.0)), Diopters(-2.0));
    assert_eq!(m.command_for(Diopters(-40.0)), Diopters(2.0));
    assert_eq!(m.command_for(Diopters(f32::INFINITY)), Diopters(-2.0));
    assert_eq!(m.command_for(Diopters(-1e30)), Diopters(2.0));
    // NaN stays NaN, so that callers drop it rather than command a range end.
    assert!(m.command_for(Diopters(f32::NAN)).0.is_nan());
}

#[test]
fn calibration_fit_recovers_a_nonlinear_map_through_noise() {
    // The layout's map plus a lens nonlinearity, sampled every 0.25 D with ±0.02 D of
    // deterministic noise; the fitted table is within 0.03 D of the true map everywhere.
    let l = eyepiece();
    let truth = |c: f64| l.demand_at(c) + 0.03 * c * c;
    let points: Vec<(f64, f64)> = (0..=16)
        .map(|k| {
            let c = -2.0 + 0.25 * f64::from(k);
            (c, truth(c) + 0.02 * (7.3 * c + 1.1).sin())
        })
        .collect();
    let fit = CalibrationFit::fit(&points, FitLimits::default()).unwrap();
    assert!(fit.rms_d < 0.02, "{}", fit.rms_d);
    let table = fit.table("fit").unwrap();
    for k in 0..=200 {
        let c = -2.0 + 0.02 * f64::from(k);
        assert!((table.demand_at(c) - truth(c)).abs() < 0.03, "{c}");
    }
    assert_eq!(fit.residuals().count(), 17);
}

#[test]
fn calibration_fit_refusals_say_why() {
    let line = |n: usize, step: f64| -> Vec<(f64, f64)> {
        (0..n)
            .map(|k| (k as f64 * step, 2.0 - k as f64 * step))
            .collect()
    };
    assert!(matches!(
        CalibrationFit::fit(&line(4, 0.5), FitLimits::default()),
        Err(FitError::TooFewPoints { got: 4 })
    ));
    assert!(matches!(
        CalibrationFit::fit(&line(6, 1.5), FitLimits::default()),
        Err(FitError::TooSparse { .. })
    ));
    // Up then down: a parabola over the range.
    let bent: Vec<(f64, f64)> = (0..=12)
        .map(|k| {
            let c = f64::from(k) * 0.25;
            (c, 2.0 - (c - 1.5) * (c - 1.5))
        })
        .collect();
    let e = CalibrationFit::fit(&bent, FitLimits::default()).unwrap_err();
    assert!(matches!(e, FitError::NotMonotonic { .. }), "{e}");
    assert!(e.to_string().contains("turns back"), "{e}");
    // Noise of ±0.08 D everywhere.
    let noisy: Vec<(f64, f64)> = line(13, 0.25)
        .into_iter()
        .enumerate()
        .map(|(k, (c, a))| (c, a + if k % 2 == 0 { 0.08 } else { -0.08 }))
        .collect();
    let e = CalibrationFit::fit(&noisy, FitLimits::default()).unwrap_err();
    assert!(
        matches!(e, FitError::Noisy { .. }) && e.to_string().contains("rms"),
        "{e}"
    );
    // One bad reading among good ones.
    let mut outlier = line(13, 0.25);
    outlier[6].1 += 0.4;
    let e = CalibrationFit::fit(&outlier, FitLimits::default()).unwrap_err();
    assert!(e.to_string().contains("command 1.500 D"), "{e}");
    let e = CalibrationFit::fit(&[(0.0, f64::NAN); 6], FitLimits::default()).unwrap_err();
    assert!(matches!(e, FitError::NotANumber { .. }), "{e}");
}
