//! The camera model: `[camera]` intrinsics from the configuration, and which intrinsics a
//! received frame is trained and predicted with.
//!
//! Rule (the ICD's, interfaces/README.md): a `CameraFrame` that carries its own camera
//! model (1.1) is used with it (the codec has validated it against the frame's size); a
//! frame without one must have exactly the configured camera's width and height, else it is
//! a [`CameraMismatch`]: the bus core counts it, reports it as an event and never trains on
//! it, because scaling intrinsics to a different size would train a silently wrong model.
//!
//! Invariants: every [`Intrinsics`] this module returns has finite, positive focal lengths,
//! a finite principal point inside the image, and a non-zero size.

use crate::config::{ComponentConfig, ConfigError};
use gs_core::Intrinsics;
use interfaces::messages::{CameraModel, FrameHeader};

/// Largest width of predictions rendered on RENDER before any camera frame arrived.
pub(crate) const RENDER_MAX_WIDTH_PX: u32 = 64;

/// A frame without a camera model whose size is not the configured camera's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CameraMismatch {
    pub frame_width: u16,
    pub frame_height: u16,
    pub camera_width: u32,
    pub camera_height: u32,
}

impl std::fmt::Display for CameraMismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "frame is {}x{} px, the configured camera {}x{} px, and the frame carries no \
             camera model",
            self.frame_width, self.frame_height, self.camera_width, self.camera_height
        )
    }
}

/// Pinhole intrinsics of a bus camera model at a frame's size.
pub fn from_model(model: &CameraModel, width: u16, height: u16) -> Intrinsics {
    Intrinsics {
        fx: model.fx_px,
        fy: model.fy_px,
        cx: model.cx_px,
        cy: model.cy_px,
        width: u32::from(width),
        height: u32::from(height),
    }
}

/// The intrinsics a frame is used with (see the module header for the rule).
pub(crate) fn for_frame(
    configured: &Intrinsics,
    header: &FrameHeader,
    model: Option<&CameraModel>,
) -> Result<Intrinsics, CameraMismatch> {
    if let Some(model) = model {
        return Ok(from_model(model, header.width, header.height));
    }
    if (u32::from(header.width), u32::from(header.height)) != (configured.width, configured.height)
    {
        return Err(CameraMismatch {
            frame_width: header.width,
            frame_height: header.height,
            camera_width: configured.width,
            camera_height: configured.height,
        });
    }
    Ok(*configured)
}

/// The configured camera reduced by the smallest integer factor that makes it at most
/// [`RENDER_MAX_WIDTH_PX`] wide: what RENDER uses before any frame told it the size.
pub(crate) fn render_default(configured: &Intrinsics) -> Intrinsics {
    let factor = configured.width.div_ceil(RENDER_MAX_WIDTH_PX).max(1);
    if factor == 1 || configured.height / factor == 0 {
        return *configured;
    }
    configured.downsampled(factor)
}

impl ComponentConfig {
    /// The configured camera as pinhole intrinsics (validated; names the key at fault).
    pub fn camera_intrinsics(&self) -> Result<Intrinsics, ConfigError> {
        let c = &self.camera;
        let invalid = |key: &'static str, problem: String| ConfigError::Invalid { key, problem };
        if c.distortion != "none" {
            return Err(invalid(
                "camera.distortion",
                format!(
                    "{:?} is not supported (only \"none\": send undistorted images)",
                    c.distortion
                ),
            ));
        }
        for (key, size) in [
            ("camera.width_px", c.width_px),
            ("camera.height_px", c.height_px),
        ] {
            if size == 0 {
                return Err(invalid(key, "must be at least 1".into()));
            }
        }
        for (key, f) in [("camera.fx_px", c.fx_px), ("camera.fy_px", c.fy_px)] {
            if !(f.is_finite() && f > 0.0) {
                return Err(invalid(
                    key,
                    format!("{f} is not a finite positive focal length"),
                ));
            }
        }
        for (key, centre, size) in [
            ("camera.cx_px", c.cx_px, c.width_px),
            ("camera.cy_px", c.cy_px, c.height_px),
        ] {
            if !(centre.is_finite() && (0.0..=f32::from(size)).contains(&centre)) {
                return Err(invalid(
                    key,
                    format!("{centre} is not inside the image (0..={size} px)"),
                ));
            }
        }
        Ok(Intrinsics {
            fx: c.fx_px,
            fy: c.fy_px,
            cx: c.cx_px,
            cy: c.cy_px,
            width: u32::from(c.width_px),
            height: u32::from(c.height_px),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use interfaces::messages::{Distortion, PixelFormat};

    fn header(width: u16, height: u16) -> FrameHeader {
        FrameHeader {
            frame_id: 1,
            time_us: 2,
            width,
            height,
            format: PixelFormat::Rgb8,
        }
    }

    #[test]
    fn frames_use_their_own_model_else_the_configured_camera_of_the_same_size() {
        let configured = ComponentConfig::default().camera_intrinsics().unwrap();
        let (w, h) = (configured.width as u16, configured.height as u16);
        assert_eq!(for_frame(&configured, &header(w, h), None), Ok(configured));
        let mismatch = for_frame(&configured, &header(w / 2, h / 2), None).unwrap_err();
        assert_eq!(
            (mismatch.frame_width, mismatch.camera_width),
            (w / 2, configured.width)
        );
        let model = CameraModel {
            fx_px: 100.0,
            fy_px: 90.0,
            cx_px: 10.0,
            cy_px: 5.0,
            distortion: Distortion::None,
        };
        let own = for_frame(&configured, &header(20, 12), Some(&model)).unwrap();
        assert_eq!(
            (own.fx, own.fy, own.cx, own.cy, own.width, own.height),
            (100.0, 90.0, 10.0, 5.0, 20, 12)
        );
    }

    #[test]
    fn render_default_fits_64_px_and_keeps_the_field_of_view() {
        let speed = ComponentConfig::default().camera_intrinsics().unwrap();
        let small = render_default(&speed);
        assert!(small.width <= RENDER_MAX_WIDTH_PX && small.width > 0 && small.height > 0);
        assert!((small.fov_x_rad() - speed.fov_x_rad()).abs() < 1e-5);
        let tiny = Intrinsics::from_fov_x(0.5, 16, 16);
        assert_eq!(render_default(&tiny), tiny);
    }
}
