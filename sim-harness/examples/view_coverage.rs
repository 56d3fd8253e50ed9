//! How much of what the evaluation views ask for a rendezvous sequence ever shows.
//!
//! Reads a dataset written by `sim-harness generate` (`telemetry.jsonl` and
//! `eval/telemetry.jsonl`) and prints, for the lit sequence frames against the evaluation
//! views, in the target body frame: the range of viewpoint and Sun angles to the tumble
//! axis, the Sun phase angles, and the fraction of evaluation views with a frame whose
//! viewpoint (Sun) lies within 30 (15) degrees, and with one frame close in both at once.
//! The appearance of a view depends on its Sun and viewpoint together, so the joint
//! fraction is what the L2 rung of the accuracy ladder can expect a model to have seen
//! (`docs/results/accuracy.md`).
//!
//! Usage: `cargo run --release -p sim-harness --example view_coverage -- DATASET [--axis X,Y,Z]`
//! (`--axis`: the tumble axis in the body frame, default `1,0,0`).

use std::path::Path;

use glam::{DQuat, DVec3};

const USAGE: &str = "view_coverage: what the evaluation views ask for against what a sequence shows

usage: cargo run --release -p sim-harness --example view_coverage -- DATASET [--axis X,Y,Z]
  DATASET       a folder written by `sim-harness generate` (telemetry.jsonl, eval/)
  --axis X,Y,Z  the tumble axis, target body frame (default 1,0,0)";

const VIEW_NEAR_DEG: f64 = 30.0;
const SUN_NEAR_DEG: f64 = 15.0;

/// Viewpoint (unit, target to camera) and Sun (unit) of one lit image, target body frame.
struct Look {
    view: DVec3,
    sun: DVec3,
}

fn vec3(v: &serde_json::Value, key: &str, line: usize) -> Result<Vec<f64>, String> {
    v.get(key)
        .and_then(|a| a.as_array())
        .map(|a| {
            a.iter()
                .filter_map(serde_json::Value::as_f64)
                .collect::<Vec<f64>>()
        })
        .filter(|a| a.len() == 3 || (key.starts_with("q_") && a.len() == 4))
        .ok_or_else(|| format!("line {line}: missing or malformed {key:?}"))
}

/// The lit images of one `telemetry.jsonl`.
fn load(path: &Path) -> Result<Vec<Look>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut looks = Vec::new();
    for (i, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let v: serde_json::Value = serde_json::from_str(line)
            .map_err(|e| format!("{} line {}: {e}", path.display(), i + 1))?;
        if v.get("eclipse").and_then(serde_json::Value::as_bool) == Some(true) {
            continue;
        }
        let q = vec3(&v, "q_camera_from_target_wxyz", i + 1)?;
        let t = vec3(&v, "t_camera_from_target_m", i + 1)?;
        let s = vec3(&v, "sun_target_body", i + 1)?;
        let q_camera_from_target = DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize();
        let camera_centre = -(q_camera_from_target.inverse() * DVec3::new(t[0], t[1], t[2]));
        let (view, sun) = (
            camera_centre.normalize(),
            DVec3::new(s[0], s[1], s[2]).normalize(),
        );
        if !(view.is_finite() && sun.is_finite()) {
            return Err(format!(
                "{} line {}: degenerate pose or Sun",
                path.display(),
                i + 1
            ));
        }
        looks.push(Look { view, sun });
    }
    Ok(looks)
}

fn deg(a: DVec3, b: DVec3) -> f64 {
    a.angle_between(b).to_degrees()
}

fn span(values: impl Iterator<Item = f64>) -> (f64, f64, f64) {
    let mut v: Vec<f64> = values.collect();
    v.sort_by(f64::total_cmp);
    (v[0], v[v.len() / 2], v[v.len() - 1])
}

fn run() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.is_empty() || args.iter().any(|a| a == "--help" || a == "-h") {
        println!("{USAGE}");
        return Ok(());
    }
    let axis = match args.iter().position(|a| a == "--axis") {
        Some(i) => {
            let parts: Result<Vec<f64>, _> = args
                .get(i + 1)
                .ok_or("--axis needs X,Y,Z")?
                .split(',')
                .map(str::parse)
                .collect();
            match parts.map_err(|e| format!("--axis: {e}"))?.as_slice() {
                [x, y, z] if DVec3::new(*x, *y, *z).length() > 0.0 => {
                    DVec3::new(*x, *y, *z).normalize()
                }
                _ => return Err("--axis needs three numbers, not all zero".into()),
            }
        }
        None => DVec3::X,
    };
    let dataset = Path::new(&args[0]);
    let frames = load(&dataset.join("telemetry.jsonl"))?;
    let eval = load(&dataset.join("eval").join("telemetry.jsonl"))?;
    if frames.is_empty() || eval.is_empty() {
        return Err("no lit frames or no evaluation views in the dataset".into());
    }
    println!(
        "{}: {} lit frames, {} evaluation views (target body frame)",
        dataset.display(),
        frames.len(),
        eval.len()
    );
    for (what, looks) in [("frames", &frames), ("evaluation views", &eval)] {
        let (v0, vm, v1) = span(looks.iter().map(|l| deg(l.view, axis)));
        let (s0, sm, s1) = span(looks.iter().map(|l| deg(l.sun, axis)));
        let (p0, pm, p1) = span(looks.iter().map(|l| deg(l.view, l.sun)));
        println!(
            "  {what:16}: viewpoint to axis {v0:5.1}..{v1:5.1} deg (median {vm:5.1}), \
             Sun to axis {s0:5.1}..{s1:5.1} (median {sm:5.1}), phase {p0:5.1}..{p1:5.1} (median {pm:5.1})"
        );
    }
    let mut near_view = 0;
    let mut near_sun = 0;
    let mut near_both = 0;
    let mut joint = Vec::with_capacity(eval.len());
    for e in &eval {
        let mut best_view = f64::INFINITY;
        let mut best_sun = f64::INFINITY;
        let mut best_joint = f64::INFINITY;
        for f in &frames {
            let (dv, ds) = (deg(e.view, f.view), deg(e.sun, f.sun));
            best_view = best_view.min(dv);
            best_sun = best_sun.min(ds);
            best_joint = best_joint.min((dv / VIEW_NEAR_DEG).max(ds / SUN_NEAR_DEG));
        }
        near_view += usize::from(best_view <= VIEW_NEAR_DEG);
        near_sun += usize::from(best_sun <= SUN_NEAR_DEG);
        near_both += usize::from(best_joint <= 1.0);
        joint.push(best_joint);
    }
    let pct = |n: usize| 100.0 * n as f64 / eval.len() as f64;
    println!(
        "  evaluation views with a frame's viewpoint within {VIEW_NEAR_DEG} deg: {:.0} %; \
         a frame's Sun within {SUN_NEAR_DEG} deg: {:.0} %; one frame within both: {:.0} %",
        pct(near_view),
        pct(near_sun),
        pct(near_both)
    );
    let (_, joint_median, _) = span(joint.into_iter());
    println!(
        "  median over evaluation views of the nearest frame in both (max of view / {VIEW_NEAR_DEG} deg, Sun / {SUN_NEAR_DEG} deg): {joint_median:.2}"
    );
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("view_coverage: {e}");
        std::process::exit(1);
    }
}
