//! A Sun-aware model baked for one Sun vector and one viewpoint, as an ordinary 3DGS PLY.
//!
//! Viewers know SH colour only. Configuration (a) is written as it is (its SH already is
//! the colour model). For (b)-(d), Phi's colour for the given Sun and the view vector from
//! each Gaussian to `camera_centre` (times the Lambertian factor when `config.shading` is
//! on) becomes the SH DC term (degree 0), multiplied for (c)-(d) by the refined visibility
//! `V'` of that Sun: the file shows the target as lit and shadowed for that geometry. A
//! model that blends linear radiance (`ColourSpace::Linear`) has its baked colours
//! sRGB-encoded per Gaussian, since viewers blend what they read as sRGB.
//! Geometry and opacity are copied unchanged, and a learned shading normal becomes the
//! PLY's `nx ny nz`. Features,
//! latents and network weights are not representable in a PLY: they live in the checkpoint.

use std::io::Write;
use std::path::Path;

use glam::Vec3;

use crate::model::{GaussianModel, ModelLayout, Param};
use crate::ply::write_ply;
use crate::sh::rgb_to_sh_dc;

use super::config::ShadowRefinement;
use super::error::SunAwareError;
use super::model::SunAwareModel;
use super::shading::{assemble_phi_input, shade_forward, Shading};

/// The colour (and for c-d shadow) of every Gaussian for one Sun and viewpoint, `N * 3`.
pub fn baked_colours(
    model: &SunAwareModel,
    camera_centre: Vec3,
    sun_dir: Vec3,
) -> Result<Vec<f32>, SunAwareError> {
    let n = model.len();
    let p = &model.gaussians.params;
    let Some(phi) = &model.appearance else {
        return Ok(crate::sh::sh_to_rgb(
            p,
            model.gaussians.layout().sh_degree,
            camera_centre,
        )?);
    };
    if !(sun_dir.is_finite() && sun_dir.length_squared() > 1e-12) {
        return Err(SunAwareError::BadObservation(format!(
            "Sun vector {sun_dir:?} is not a finite non-zero vector"
        )));
    }
    let sun = sun_dir.normalize();
    let all: Vec<u32> = (0..n as u32).collect();
    let mut input = Vec::new();
    assemble_phi_input(phi, p, &all, camera_centre, sun, &mut input)?;
    let mut rgb = phi.mlp.forward(&input, n)?;
    if model.config.shading != Shading::None {
        shade_forward(
            model.config.shading,
            p,
            &all,
            camera_centre,
            sun,
            model.config.shading_ambient,
            &mut rgb,
        );
    }
    if let Some(psi) = &model.shadow {
        let vis = super::sun_visibility::sun_visibility(
            &model.gaussians,
            sun,
            camera_centre,
            &model.scene_box,
            &model.config.light,
            model.config.near_m,
        )?;
        psi.assemble_input(
            &all,
            &vis,
            p.get(Param::ShadowLatent),
            p.get(Param::Mean),
            sun.to_array(),
            &model.scene_box,
            &mut input,
        )?;
        let refined = psi.mlp.forward(&input, n)?;
        let multiply = model.config.shadow_refinement == ShadowRefinement::Multiply;
        for ((c, s), v_i) in rgb.chunks_exact_mut(3).zip(&refined).zip(&vis) {
            let shadow = if multiply {
                model.config.shadow_gain * s * v_i
            } else {
                *s
            };
            for v in c {
                *v *= shadow;
            }
        }
    }
    // Viewers read sRGB: a linear model's colours are encoded per Gaussian (the renderer
    // encodes per pixel after blending, which a viewer cannot do).
    let space = model.config.colour_space;
    rgb.iter_mut().for_each(|v| *v = space.to_srgb(*v));
    Ok(rgb)
}

/// A plain SH model of the baked colours (degree 0 for b-d; configuration a unchanged).
pub fn bake(
    model: &SunAwareModel,
    camera_centre: Vec3,
    sun_dir: Vec3,
) -> Result<GaussianModel, SunAwareError> {
    if model.appearance.is_none() {
        let mut out = GaussianModel::new(ModelLayout::sh(model.gaussians.layout().sh_degree))?;
        let src = &model.gaussians.params;
        out.params.push_zeros(model.len());
        for p in [
            Param::Mean,
            Param::LogScale,
            Param::Rotation,
            Param::OpacityLogit,
            Param::ShDc,
            Param::ShRest,
        ] {
            out.params.get_mut(p).copy_from_slice(src.get(p));
        }
        return Ok(out);
    }
    let rgb = baked_colours(model, camera_centre, sun_dir)?;
    let src = &model.gaussians.params;
    // A learned shading normal goes to the PLY's nx, ny, nz.
    let mut out = GaussianModel::new(ModelLayout {
        normal_dim: src.dim(Param::Normal),
        ..ModelLayout::sh(0)
    })?;
    out.params.push_zeros(model.len());
    for p in [
        Param::Mean,
        Param::LogScale,
        Param::Rotation,
        Param::OpacityLogit,
        Param::Normal,
    ] {
        out.params.get_mut(p).copy_from_slice(src.get(p));
    }
    for (dc, &c) in out.params.get_mut(Param::ShDc).iter_mut().zip(&rgb) {
        *dc = rgb_to_sh_dc(c);
    }
    Ok(out)
}

/// Writes the baked model as a 3DGS PLY.
pub fn write_baked_ply<W: Write>(
    model: &SunAwareModel,
    camera_centre: Vec3,
    sun_dir: Vec3,
    out: W,
) -> Result<(), SunAwareError> {
    let baked = bake(model, camera_centre, sun_dir)?;
    write_ply(&baked, out)?;
    Ok(())
}

/// Writes the baked model to `path`.
pub fn save_baked_ply(
    model: &SunAwareModel,
    camera_centre: Vec3,
    sun_dir: Vec3,
    path: impl AsRef<Path>,
) -> Result<(), SunAwareError> {
    let file = std::fs::File::create(path)?;
    write_baked_ply(model, camera_centre, sun_dir, file)
}
