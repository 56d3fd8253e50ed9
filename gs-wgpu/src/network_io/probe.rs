//! [`NetworkIoProbe`]: device buffers from host data and back, for the tests of
//! [`super::NetworkIo`] outside the crate.

use crate::{bytes_f32, bytes_u32, f32_bytes, u32_bytes, GpuContext, GpuError};

/// Host data into device buffers and back, for tests and diagnostics outside the crate
/// that record [`NetworkIo`](super::NetworkIo)'s `encode_*` functions (the context's buffer helpers are
/// crate-private): buffers from host slices, an encoder, one submission and readback.
#[derive(Debug)]
pub struct NetworkIoProbe {
    ctx: GpuContext,
}

impl NetworkIoProbe {
    pub fn new(ctx: &GpuContext) -> Self {
        Self { ctx: ctx.clone() }
    }

    /// A storage buffer holding `data` (at least 16 bytes).
    pub fn buffer_f32(&self, label: &str, data: &[f32]) -> wgpu::Buffer {
        self.ctx.storage_init(label, &f32_bytes(data))
    }

    /// A storage buffer holding `data` (at least 16 bytes).
    pub fn buffer_u32(&self, label: &str, data: &[u32]) -> wgpu::Buffer {
        self.ctx.storage_init(label, &u32_bytes(data))
    }

    pub fn encoder(&self) -> wgpu::CommandEncoder {
        self.ctx.encoder("netio probe")
    }

    /// Submits `encoder` and reads back the first `len` f32 of each buffer.
    pub fn finish_f32(
        &self,
        encoder: wgpu::CommandEncoder,
        buffers: &[(&wgpu::Buffer, usize)],
    ) -> Result<Vec<Vec<f32>>, GpuError> {
        let ranges: Vec<(&wgpu::Buffer, u64)> = buffers
            .iter()
            .map(|(b, len)| (*b, *len as u64 * 4))
            .collect();
        Ok(self
            .ctx
            .read_back(encoder, &ranges)?
            .iter()
            .map(|b| bytes_f32(b))
            .collect())
    }

    /// The first `len` u32 of `buffer` (after everything submitted so far).
    pub fn read_u32(&self, buffer: &wgpu::Buffer, len: usize) -> Result<Vec<u32>, GpuError> {
        let bytes = self
            .ctx
            .read_back(self.encoder(), &[(buffer, len as u64 * 4)])?;
        Ok(bytes_u32(&bytes[0]))
    }
}
