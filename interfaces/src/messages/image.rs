//! Image-carrying messages: camera frames in, rendered predictions out. Pixels are row-major,
//! top row first, tightly packed (RGB8: 3 bytes per pixel R, G, B; Gray8: 1 byte). A mask is
//! one byte per pixel, 0 = background, non-zero = target. Pixel bytes are borrowed from the
//! caller's buffer. Sizes are checked against width x height x bytes per pixel.
//!
//! `CameraFrame` 1.1 appends an optional [`CameraModel`] (pinhole intrinsics of this frame);
//! a frame without it is byte-identical to 1.0 and the receiver uses its configured camera.

use super::validate::{check_finite, check_len, check_unit_norm, ValidationError};
use super::{appended, bytes, port, Direction, Message, Version};
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PixelFormat {
    Rgb8,
    Gray8,
}

impl PixelFormat {
    pub const fn bytes_per_pixel(self) -> usize {
        match self {
            PixelFormat::Rgb8 => 3,
            PixelFormat::Gray8 => 1,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameHeader {
    pub frame_id: u32,
    /// Exposure mid-time (camera frames) or render time (predictions), microseconds.
    pub time_us: u64,
    pub width: u16,
    pub height: u16,
    pub format: PixelFormat,
}

impl FrameHeader {
    /// Largest possible encoding, bytes.
    pub const MAX_ENCODED_LEN: usize = 22;

    // Saturating: on a 32-bit flight computer 65535 x 65535 x 3 overflows usize; a saturated
    // size can never match a real buffer, so validation still fails cleanly.
    pub fn pixel_count(&self) -> usize {
        usize::from(self.width).saturating_mul(usize::from(self.height))
    }

    pub fn image_bytes(&self) -> usize {
        self.pixel_count()
            .saturating_mul(self.format.bytes_per_pixel())
    }

    fn check_image(&self, pixels: &[u8]) -> Result<(), ValidationError> {
        if self.width == 0 || self.height == 0 {
            return Err(ValidationError::ZeroSize {
                field: "width/height",
            });
        }
        check_len("pixels", self.image_bytes(), pixels.len())
    }
}

/// Lens distortion of a [`CameraModel`]; the wire value is the variant index (append only).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Distortion {
    /// An ideal pinhole (or images already undistorted by the camera).
    None,
}

/// Pinhole intrinsics of one frame, pixels, for the image size in its header. Pixel centres
/// are at integer + 0.5 (the pixel (u, v) covers [u, u+1) x [v, v+1)); camera axes as in
/// `TargetPose` (+x right, +y down, +z along the boresight).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    pub fx_px: f32,
    pub fy_px: f32,
    pub cx_px: f32,
    pub cy_px: f32,
    pub distortion: Distortion,
}

impl CameraModel {
    /// Encoded size, bytes.
    pub const ENCODED_LEN: usize = 17;

    /// Focal lengths finite and positive, principal point finite and inside the image
    /// `width` x `height` (edges included).
    pub fn check(&self, width: u16, height: u16) -> Result<(), ValidationError> {
        check_finite("camera", &[self.fx_px, self.fy_px, self.cx_px, self.cy_px])?;
        if self.fx_px <= 0.0 || self.fy_px <= 0.0 {
            return Err(ValidationError::OutOfRange {
                field: "camera focal length",
            });
        }
        let inside = |c: f32, size: u16| (0.0..=f32::from(size)).contains(&c);
        if !inside(self.cx_px, width) || !inside(self.cy_px, height) {
            return Err(ValidationError::OutOfRange {
                field: "camera principal point",
            });
        }
        Ok(())
    }
}

/// One camera image with optional target mask.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraFrame<'a> {
    pub header: FrameHeader,
    #[serde(borrow, serialize_with = "bytes::serialize_option")]
    pub mask: Option<&'a [u8]>,
    #[serde(borrow, serialize_with = "bytes::serialize")]
    pub pixels: &'a [u8],
    /// 1.1: this frame's intrinsics; `None` (and every 1.0 frame): the receiver's configured
    /// camera. Left off the wire when `None`.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "appended::deserialize"
    )]
    pub camera: Option<CameraModel>,
}

impl Message for CameraFrame<'_> {
    const PORT_ID: u16 = port::CAMERA_FRAME;
    const VERSION: Version = Version { major: 1, minor: 1 };
    const NAME: &'static str = "CameraFrame";
    const DIRECTION: Direction = Direction::ToComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        self.header.check_image(self.pixels)?;
        if let Some(mask) = self.mask {
            check_len("mask", self.header.pixel_count(), mask.len())?;
        }
        if let Some(camera) = &self.camera {
            camera.check(self.header.width, self.header.height)?;
        }
        Ok(())
    }
}

/// Why a prediction was rendered.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PredictionSource {
    /// Rendered for an accepted camera frame, before training on it.
    ObservedFrame { frame_id: u32 },
    /// Rendered on a RENDER command.
    Command { sequence: u32 },
}

/// What the model predicts the camera sees at a pose under a Sun direction.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderedPrediction<'a> {
    pub header: FrameHeader,
    pub source: PredictionSource,
    /// Pose rendered for (same convention as TargetPose).
    pub q_camera_from_target: [f32; 4],
    pub t_camera_from_target_m: [f32; 3],
    /// Unit Sun direction in the target body frame the image was lit with.
    pub sun_target: [f32; 3],
    /// PSNR in dB against the observed frame, when there is one.
    pub psnr_db: Option<f32>,
    /// SSIM (11x11 Gaussian window) against the observed frame, when there is one.
    pub ssim: Option<f32>,
    #[serde(borrow, serialize_with = "bytes::serialize")]
    pub pixels: &'a [u8],
}

impl RenderedPrediction<'_> {
    /// Largest encoding of everything but the pixel bytes and their length varint, bytes.
    pub const MAX_FIXED_ENCODED_LEN: usize = 78;
}

impl Message for RenderedPrediction<'_> {
    const PORT_ID: u16 = port::RENDERED_PREDICTION;
    const VERSION: Version = Version { major: 1, minor: 0 };
    const NAME: &'static str = "RenderedPrediction";
    const DIRECTION: Direction = Direction::FromComponent;

    fn validate(&self) -> Result<(), ValidationError> {
        self.header.check_image(self.pixels)?;
        check_unit_norm("q_camera_from_target", &self.q_camera_from_target)?;
        check_finite("t_camera_from_target_m", &self.t_camera_from_target_m)?;
        check_unit_norm("sun_target", &self.sun_target)?;
        if let Some(psnr) = self.psnr_db {
            // PSNR of identical images is +inf: the sender clamps it to a finite value.
            check_finite("psnr_db", &[psnr])?;
        }
        if let Some(ssim) = self.ssim {
            check_finite("ssim", &[ssim])?;
            if !(-1.0..=1.0).contains(&ssim) {
                return Err(ValidationError::OutOfRange { field: "ssim" });
            }
        }
        Ok(())
    }
}
