//! The rasterizer's switches against the CPU: early termination off, blending only the
//! selected tiles (`RasterSettings::blend_tiles`), the contribution pass, the switches'
//! input checks, and channels the kernels must never read.

use super::*;

/// `RasterSettings::early_termination = false` (every pixel blends its whole list, down
/// to T = 1.2e-38): images and gradients against the CPU with the tolerances above, on a
/// scene where the switch changes many pixels.
#[test]
fn early_termination_off_matches_cpu() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(31, 2000, 3, false);
    let stopped = render(&scene.camera, &scene.view(), &scene.settings).unwrap();
    scene.settings.early_termination = false;
    let (cpu, out) = compare_forward(&gpu, &scene, "early termination off");
    // The switch matters here: with the stop a pixel keeps T >= 1e-4, without it the
    // alpha of a pixel that stopped grows by about that much.
    let changed = count_above(&cpu.alpha, &stopped.alpha, 2e-5);
    eprintln!(
        "{changed} of {} pixels change by more than 2e-5 (at most {:.2e})",
        cpu.alpha.len(),
        max_abs_diff(&cpu.alpha, &stopped.alpha)
    );
    assert!(changed > 100, "{changed} pixels changed");
    assert!(count_above(&out.alpha, &stopped.alpha, 2e-5) >= changed / 2);
    compare_grads(&gpu, &scene, 31, GpuOptions::default());
}

/// Seeded tile selection over `scene`'s image: about half the tiles, from a mask.
fn holed_selection(scene: &Scene, seed: u64) -> TileSelection {
    let (w, h) = (
        scene.camera.intrinsics.width,
        scene.camera.intrinsics.height,
    );
    let grid = TileGrid::new(w, h);
    let mut rng = SplitMix64::new(seed);
    let mut mask = vec![0.0f32; (w * h) as usize];
    for t in 0..grid.n_tiles() {
        if rng.next_u64() & 1 == 0 {
            let r = grid.tile_rect(t);
            mask[(r.y0 * w + r.x0) as usize] = 1.0;
        }
    }
    let selection = TileSelection::from_mask(&mask, w, h, 0).unwrap();
    let active = selection.active_count();
    assert!(
        active > 0 && active < grid.n_tiles(),
        "{active} tiles active"
    );
    selection
}

/// `RasterSettings::blend_tiles` with holes: skipped tiles' pixels are the CPU's bits
/// exactly (background, alpha 0, depth 0); active tiles are the GPU's own full render,
/// bit for bit, and match the CPU with the tolerances above; gradients match the CPU's
/// (which get nothing from skipped tiles) on both backward kernels.
#[test]
fn blend_tiles_match_cpu() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(32, 2000, 3, false);
    let full = gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .unwrap();
    let selection = holed_selection(&scene, 32);
    scene.settings.blend_tiles = Some(selection.clone());
    let (cpu, out) = compare_forward(&gpu, &scene, "blend_tiles");
    let grid = TileGrid::new(out.width, out.height);
    let (w, nc) = (out.width as usize, out.n_channels);
    let mut skipped_covered = 0;
    for t in 0..grid.n_tiles() {
        let r = grid.tile_rect(t);
        for y in r.y0 as usize..r.y1 as usize {
            for x in r.x0 as usize..r.x1 as usize {
                let p = y * w + x;
                let colour = |o: &[f32]| -> Vec<u32> {
                    o[p * nc..p * nc + nc].iter().map(|v| v.to_bits()).collect()
                };
                if selection.is_active(t) {
                    assert_eq!(colour(&out.color), colour(&full.color), "pixel {x},{y}");
                    assert_eq!(out.alpha[p].to_bits(), full.alpha[p].to_bits());
                    assert_eq!(out.depth[p].to_bits(), full.depth[p].to_bits());
                } else {
                    assert_eq!(colour(&out.color), colour(&cpu.color), "pixel {x},{y}");
                    let bg: Vec<u32> = scene
                        .settings
                        .background
                        .iter()
                        .map(|v| v.to_bits())
                        .collect();
                    assert_eq!(colour(&out.color), bg);
                    assert_eq!(out.alpha[p].to_bits(), 0.0f32.to_bits());
                    assert_eq!(out.depth[p].to_bits(), 0.0f32.to_bits());
                    assert_eq!(cpu.alpha[p].to_bits(), 0.0f32.to_bits());
                    assert_eq!(cpu.depth[p].to_bits(), 0.0f32.to_bits());
                    skipped_covered += usize::from(full.alpha[p] > 0.5);
                }
            }
        }
    }
    // The skip hides real content.
    assert!(
        skipped_covered > 100,
        "{skipped_covered} covered pixels skipped"
    );
    let (_, g) = compare_grads(&gpu, &scene, 32, GpuOptions::default());
    // Gaussians seen only in skipped tiles get no gradient at all.
    let full_grads = {
        let full_settings = RasterSettings {
            blend_tiles: None,
            ..scene.settings.clone()
        };
        let (dc, da, dd) = pixel_grads(&scene, 32 ^ 0x5EED);
        let pg = PixelGrads {
            d_color: &dc,
            d_alpha: Some(&da),
            d_depth: Some(&dd),
        };
        let f = gpu
            .render(&scene.camera, &scene.view(), &full_settings)
            .unwrap();
        gpu.render_backward(&scene.camera, &full_settings, &f, &pg)
            .unwrap()
    };
    let silenced = (0..scene.opacity_logits.len())
        .filter(|&i| g.d_opacity_logits[i] == 0.0 && full_grads.d_opacity_logits[i] != 0.0)
        .count();
    assert!(silenced > 20, "{silenced} Gaussians lost their gradient");
    // The workgroup-reduction kernel (and the gather) skip the same tiles.
    let Some(det) = context(GpuOptions {
        deterministic: true,
        ..GpuOptions::default()
    }) else {
        return;
    };
    compare_grads(
        &GpuRasterizer::new(det).unwrap(),
        &scene,
        32,
        GpuOptions {
            deterministic: true,
            ..GpuOptions::default()
        },
    );
}

/// Per Gaussian: blended into a pixel of an active tile of `selection`, from the CPU's own
/// projection, depth order, bins and alpha-only tile walk (what
/// `PreparedView::contributing` computes, tile by tile).
fn cpu_contributing_in(scene: &Scene, selection: Option<&TileSelection>) -> Vec<bool> {
    let s = &scene.settings;
    let (w, h) = (
        scene.camera.intrinsics.width,
        scene.camera.intrinsics.height,
    );
    let frame = camera_frame(&scene.camera, s.near_m).unwrap();
    let mode = AlphaMode {
        smooth: s.smooth_cutoff,
    };
    let bare = GaussianView {
        channels: &[],
        n_channels: 0,
        ..scene.view()
    };
    let projected = project_splats_with(&frame, &bare, mode, w, h, s.cull_outside_frustum);
    let gaussian_of_rank = depth_order(&projected.splats);
    let splats: Vec<Splat> = gaussian_of_rank
        .iter()
        .filter_map(|&g| projected.splats[g as usize])
        .collect();
    let rects: Vec<PixelRect> = splats.iter().map(|s| s.rect).collect();
    let grid = TileGrid::new(w, h);
    let bins = bin_tiles(&grid, &rects);
    let mut out = vec![false; bare.len()];
    for t in 0..grid.n_tiles() {
        if selection.is_some_and(|sel| !sel.is_active(t)) {
            continue;
        }
        let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
        let mut flags = vec![0u8; list.len()];
        tile_contributions(
            &grid.tile_rect(t),
            list,
            &splats,
            mode,
            s.early_termination,
            &mut flags,
        );
        for (&f, &rank) in flags.iter().zip(list) {
            if f & ENTRY_BLENDS != 0 {
                out[gaussian_of_rank[rank as usize] as usize] = true;
            }
        }
    }
    out
}

/// The device's contribution pass against the CPU's `PreparedView::contributing` on
/// random views (camera positions and scenes), with early termination on and off and in
/// smooth mode, and against the CPU's tile walk restricted to a selection's tiles.
/// Exact equality: the pass evaluates alpha and the transmittance with the blend's
/// operations, which agree with the CPU's on these scenes bit for bit (a fused multiply-add
/// or an ulp in exp could move an alpha across 1/255 or a T across the stop and so flip a
/// Gaussian seen in one pixel only; none does here, and the test would show it).
#[test]
fn contribution_flags_match_cpu() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    for seed in 0..4u64 {
        // Dense, so that many projected Gaussians hide behind others.
        let mut scene = random_scene(40 + seed, 8000, 3, seed == 3);
        let mut rng = SplitMix64::new(seed);
        let eye = Vec3::new(
            rng.uniform(-1.5, 1.5),
            rng.uniform(-1.0, 1.0),
            rng.uniform(-4.5, -3.0),
        );
        scene.camera = Camera::look_at(
            scene.camera.intrinsics,
            eye,
            Vec3::new(rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        );
        scene.settings.early_termination = seed != 1;
        let view = scene.view();
        let prepared = prepare_view(&scene.camera, &view, &scene.settings).unwrap();
        let cpu = prepared.contributing();
        let survived = prepared.survived();
        let n_cpu = cpu.iter().filter(|&&c| c).count();
        let n_survived = survived.iter().filter(|&&c| c).count();
        eprintln!("view {seed}: {n_cpu} of {n_survived} projected Gaussians contribute");
        assert!(
            n_cpu > 100 && n_cpu + 20 < n_survived,
            "{n_cpu} of {n_survived}"
        );
        // The reference walk is the CPU's own pass where no tile is left out.
        assert_eq!(cpu_contributing_in(&scene, None), cpu);
        let got = gpu
            .contributing(&scene.camera, &view, &scene.settings)
            .unwrap();
        let differ: Vec<usize> = (0..cpu.len()).filter(|&g| got[g] != cpu[g]).collect();
        assert!(
            differ.is_empty(),
            "view {seed}: Gaussians {differ:?} differ"
        );

        let selection = holed_selection(&scene, seed);
        scene.settings.blend_tiles = Some(selection.clone());
        let expected = cpu_contributing_in(&scene, Some(&selection));
        let n_expected = expected.iter().filter(|&&c| c).count();
        assert!(
            n_expected > 50 && n_expected < n_cpu,
            "{n_expected} of {n_cpu}"
        );
        let got = gpu
            .contributing(&scene.camera, &scene.view(), &scene.settings)
            .unwrap();
        let differ: Vec<usize> = (0..cpu.len()).filter(|&g| got[g] != expected[g]).collect();
        assert!(
            differ.is_empty(),
            "view {seed}, tiles: Gaussians {differ:?} differ"
        );
    }
}

/// The switches' inputs are checked as on the CPU: a tile selection built for another
/// image size is an error (render and contribution pass), and an empty model has no
/// contribution flags.
#[test]
fn switch_inputs_are_checked() {
    let Some(ctx) = context(GpuOptions::default()) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(33, 50, 3, false);
    let (w, h) = (
        scene.camera.intrinsics.width,
        scene.camera.intrinsics.height,
    );
    let wrong = TileSelection::from_mask(&vec![1.0; (w * 2 * h) as usize], w * 2, h, 0).unwrap();
    scene.settings.blend_tiles = Some(wrong);
    assert!(render(&scene.camera, &scene.view(), &scene.settings).is_err());
    assert!(gpu
        .render(&scene.camera, &scene.view(), &scene.settings)
        .is_err());
    assert!(gpu
        .contributing(&scene.camera, &scene.view(), &scene.settings)
        .is_err());
    scene.settings.blend_tiles = None;
    let empty = GaussianView {
        means: &[],
        log_scales: &[],
        rotations: &[],
        opacity_logits: &[],
        channels: &[],
        n_channels: 3,
    };
    let flags = gpu
        .contributing(&scene.camera, &empty, &scene.settings)
        .unwrap();
    assert!(flags.is_empty());
}

/// What the contribution flags promise the device-resident step: the blend and its
/// backward never read the channels of a Gaussian without a flag. With 1e30 in those
/// channels (any use would overflow), the image and every gradient are the same bits
/// (deterministic backward), with and without a tile selection; the flagged channels'
/// gradients are zero for the others.
#[test]
fn unflagged_channels_are_never_read() {
    let options = GpuOptions {
        deterministic: true,
        ..GpuOptions::default()
    };
    let Some(ctx) = context(options) else {
        return;
    };
    let gpu = GpuRasterizer::new(ctx).unwrap();
    let mut scene = random_scene(34, 5000, 3, false);
    for with_tiles in [false, true] {
        if with_tiles {
            scene.settings.blend_tiles = Some(holed_selection(&scene, 34));
        }
        let flags = gpu
            .contributing(&scene.camera, &scene.view(), &scene.settings)
            .unwrap();
        let hidden = flags.iter().filter(|&&f| !f).count();
        assert!(hidden > 500, "{hidden} Gaussians without a flag");
        let mut poisoned = Scene {
            channels: scene.channels.clone(),
            means: scene.means.clone(),
            log_scales: scene.log_scales.clone(),
            rotations: scene.rotations.clone(),
            opacity_logits: scene.opacity_logits.clone(),
            camera: scene.camera,
            settings: scene.settings.clone(),
            n_channels: scene.n_channels,
        };
        for (g, &f) in flags.iter().enumerate() {
            if !f {
                poisoned.channels[3 * g..3 * g + 3].fill(1e30);
            }
        }
        let (dc, da, dd) = pixel_grads(&scene, 34);
        let pg = PixelGrads {
            d_color: &dc,
            d_alpha: Some(&da),
            d_depth: Some(&dd),
        };
        let run = |s: &Scene| {
            let f = gpu.render(&s.camera, &s.view(), &s.settings).unwrap();
            let g = gpu
                .render_backward(&s.camera, &s.settings, &f, &pg)
                .unwrap();
            (f, g)
        };
        let (f0, g0) = run(&scene);
        let (f1, g1) = run(&poisoned);
        let bits = |v: &[f32]| -> Vec<u32> { v.iter().map(|x| x.to_bits()).collect() };
        assert_eq!(bits(&f0.color), bits(&f1.color), "tiles {with_tiles}");
        assert_eq!(bits(&f0.alpha), bits(&f1.alpha));
        assert_eq!(bits(&f0.depth), bits(&f1.depth));
        for (a, b) in [
            (&g0.d_means, &g1.d_means),
            (&g0.d_log_scales, &g1.d_log_scales),
            (&g0.d_rotations, &g1.d_rotations),
            (&g0.d_opacity_logits, &g1.d_opacity_logits),
            (&g0.d_channels, &g1.d_channels),
            (&g0.mean2d_grad_ndc, &g1.mean2d_grad_ndc),
        ] {
            assert_eq!(bits(a), bits(b), "tiles {with_tiles}");
        }
        for (g, &f) in flags.iter().enumerate() {
            if !f {
                assert!(g0.d_channels[3 * g..3 * g + 3].iter().all(|&v| v == 0.0));
            }
        }
    }
}
