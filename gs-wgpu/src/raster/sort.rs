//! The rasterizer's device sort and prefix sum: the exclusive scan of the per-Gaussian
//! tile counts ([`GpuRasterizer::encode_scan`]) and the stable LSD radix sort of the tile
//! keys by (tile, order bits) ([`GpuRasterizer::encode_sort_in`], [`SortKeys`]), and its
//! host wrapper for tests and benchmarks ([`GpuRasterizer::sort_keys`]).
//!
//! Invariants: the sort is stable, so keys written in ascending tie index come out in the
//! CPU's per-tile order; only the live keys (the count on the device) move; the tile
//! digits sorted are those `n_tiles` needs, after every order digit.

use super::*;

const SORT_RADIX_COMMON: &str = include_str!("../shaders/sort_radix_common.wgsl");
const SORT_RADIX_COUNT: &str = include_str!("../shaders/sort_radix_count.wgsl");
const SORT_RADIX_SCAN: &str = include_str!("../shaders/sort_radix_scan.wgsl");
const SORT_RADIX_SCATTER: &str = include_str!("../shaders/sort_radix_scatter.wgsl");
const SORT_RADIX_COPY: &str = include_str!("../shaders/sort_radix_copy.wgsl");
/// Bits of one radix sort digit (16 bins; `DIGITS` in sort_radix_common.wgsl).
const RADIX_BITS: u32 = 4;
/// Keys per radix sort workgroup (`BLOCK` in sort_radix_common.wgsl: 256 threads of 16).
const RADIX_BLOCK: u64 = 4096;
/// Order bits of a key (word 1: depth, or a receiver's limit), sorted in full.
const ORDER_BITS: u32 = 32;

/// Keys to sort on the device in place: `n_sort` vec4<u32> keys (tile, order bits, tie
/// index, 0) of which the first `min(count[count_word], n_sort)` are live. The live keys
/// end up ordered by (tile, order bits), stably, so keys written in ascending tie index
/// come out ordered by (tile, order bits, tie index); the keys past them stay as they
/// were (padding, see keygen.wgsl).
pub(crate) struct SortKeys<'a> {
    pub keys: &'a wgpu::Buffer,
    pub n_sort: u64,
    pub count: &'a wgpu::Buffer,
    pub count_word: u32,
    /// Every live key's tile word is below this: only its bits are sorted.
    pub n_tiles: u32,
    /// Names this sort's uniforms, which must differ between sorts recorded into one
    /// submission from one scratch pool. (The temporary key and histogram buffers are
    /// shared by every sort of a pool: sorts recorded one after the other run in order.)
    pub label: &'a str,
}

/// The radix sort's kernels (sort_radix_*.wgsl, after sort_radix_common.wgsl).
pub(super) struct RadixPipelines {
    count: wgpu::ComputePipeline,
    scan: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
    copy: wgpu::ComputePipeline,
}

impl RadixPipelines {
    pub(super) fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        let build =
            |label: &str, body: &str| ctx.pipeline(label, &format!("{SORT_RADIX_COMMON}\n{body}"));
        Ok(Self {
            count: build("sort_radix_count", SORT_RADIX_COUNT)?,
            scan: build("sort_radix_scan", SORT_RADIX_SCAN)?,
            scatter: build("sort_radix_scatter", SORT_RADIX_SCATTER)?,
            copy: build("sort_radix_copy", SORT_RADIX_COPY)?,
        })
    }
}

/// The radix passes that sort keys of `n_tiles` tiles: (key word, shift), least
/// significant digit first (the order bits, then the tile bits).
fn radix_digits(n_tiles: u32) -> Vec<(u32, u32)> {
    let tile_bits = u32::BITS - n_tiles.saturating_sub(1).leading_zeros();
    let order = (0..ORDER_BITS / RADIX_BITS).map(|d| (1, d * RADIX_BITS));
    let tile = (0..tile_bits.div_ceil(RADIX_BITS)).map(|d| (0, d * RADIX_BITS));
    order.chain(tile).collect()
}

impl GpuRasterizer {
    /// Exclusive prefix sum of `len` u32 values in `data`, in place (recursive over
    /// block sums). `keep` holds the temporaries until submission.
    pub(crate) fn encode_scan(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        len: u64,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        self.encode_scan_in(encoder, data, len, keep, None, 0)
    }

    /// [`Self::encode_scan`] with its temporaries from `scratch` (one set per recursion
    /// `level`).
    pub(crate) fn encode_scan_in(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        len: u64,
        keep: &mut Vec<wgpu::Buffer>,
        scratch: Option<&Scratch>,
        level: u32,
    ) -> Result<(), GpuError> {
        let blocks = len.div_ceil(256).max(1);
        let sums = storage_in(
            &self.ctx,
            scratch,
            &format!("scan sums {level}"),
            blocks * 4,
        )?;
        let params = uniform_in(
            &self.ctx,
            scratch,
            &format!("scan params {level}"),
            &u32_bytes(&[len as u32, blocks as u32, 0, 0]),
        )?;
        {
            let bind = self
                .ctx
                .bind_group(&self.scan_block, &[&params, data, &sums]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.scan_block, &bind, len);
        }
        if blocks > 1 {
            self.encode_scan_in(encoder, &sums, blocks, keep, scratch, level + 1)?;
            let bind = self.ctx.bind_group(&self.scan_add, &[&params, data, &sums]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.scan_add, &bind, len);
        }
        keep.push(sums);
        keep.push(params);
        Ok(())
    }

    /// Stable LSD radix sort of `sort`'s live keys by (tile, order bits), 4 bits per
    /// pass: per-block digit histograms, one prefix sum over them, a stable scatter into
    /// a temporary buffer and back (and a copy of the live keys when the pass count is
    /// odd). Deterministic: the histograms are integer sums and every key's destination
    /// follows from its position. Temporaries from `scratch` ("sort radix ..."), held in
    /// `keep` until submission.
    pub(crate) fn encode_sort_in(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        sort: &SortKeys,
        keep: &mut Vec<wgpu::Buffer>,
        scratch: Option<&Scratch>,
    ) -> Result<(), GpuError> {
        let ctx = &self.ctx;
        let n_blocks = sort.n_sort.div_ceil(RADIX_BLOCK);
        if sort.n_sort > u32::MAX as u64 / 2 {
            return Err(GpuError::TooLarge(format!("{} sort keys", sort.n_sort)));
        }
        let temp = storage_in(ctx, scratch, "sort radix keys", sort.n_sort * 16)?;
        let hist = storage_in(
            ctx,
            scratch,
            "sort radix histograms",
            n_blocks * (1 << RADIX_BITS) * 4,
        )?;
        let p = &self.radix;
        let digits = radix_digits(sort.n_tiles);
        let block_groups = groups_1d(n_blocks * 256);
        let mut uniforms = Vec::with_capacity(digits.len());
        for (pass, &(key_word, shift)) in digits.iter().enumerate() {
            let params = uniform_in(
                ctx,
                scratch,
                &format!("sort radix {} pass {pass}", sort.label),
                &u32_bytes(&[
                    key_word,
                    shift,
                    n_blocks as u32,
                    sort.n_sort as u32,
                    sort.count_word,
                    0,
                    0,
                    0,
                ]),
            )?;
            let (src, dst) = if pass % 2 == 0 {
                (sort.keys, &temp)
            } else {
                (&temp, sort.keys)
            };
            let count = ctx.bind_group(&p.count, &[&params, sort.count, src, &hist]);
            let scan = ctx.bind_group_at(&p.scan, &[(0, &params), (2, &hist)]);
            let scatter = ctx.bind_group(&p.scatter, &[&params, sort.count, src, &hist, dst]);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            cpass.set_pipeline(&p.count);
            cpass.set_bind_group(0, &count, &[]);
            cpass.dispatch_workgroups(block_groups.0, block_groups.1, 1);
            drop(cpass);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            cpass.set_pipeline(&p.scan);
            cpass.set_bind_group(0, &scan, &[]);
            cpass.dispatch_workgroups(1, 1, 1);
            drop(cpass);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            cpass.set_pipeline(&p.scatter);
            cpass.set_bind_group(0, &scatter, &[]);
            cpass.dispatch_workgroups(block_groups.0, block_groups.1, 1);
            drop(cpass);
            uniforms.push(params);
        }
        if let (true, Some(params)) = (digits.len() % 2 == 1, uniforms.last()) {
            let bind = ctx.bind_group(&p.copy, &[params, sort.count, &temp, sort.keys]);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut cpass, &p.copy, &bind, sort.n_sort);
        }
        keep.extend(uniforms);
        keep.extend([temp, hist]);
        Ok(())
    }

    /// Sorts `keys` on the device as a forward pass sorts its tile keys (see
    /// `Self::encode_sort_in`): `keys.len()` is the sort's capacity, `live` (kept
    /// on the device, as a pass without the entry-count readback keeps it) the number of
    /// keys sorted, `n_tiles` a bound on their tile words. Returns the whole buffer: the
    /// live keys sorted by (tile, order bits), stably, then the rest as given. For tests
    /// and benchmarks.
    pub fn sort_keys(
        &self,
        keys: &[[u32; 4]],
        live: usize,
        n_tiles: u32,
    ) -> Result<Vec<[u32; 4]>, GpuError> {
        if live > keys.len() {
            return Err(GpuError::Invalid(format!(
                "{live} live keys in a buffer of {}",
                keys.len()
            )));
        }
        if let Some(k) = keys[..live].iter().find(|k| k[0] >= n_tiles) {
            return Err(GpuError::Invalid(format!(
                "key tile {} not below the tile count {n_tiles}",
                k[0]
            )));
        }
        let ctx = &self.ctx;
        let flat: Vec<u32> = keys.iter().flatten().copied().collect();
        let buf = ctx.storage_init("sort keys", &u32_bytes(&flat));
        let count = ctx.storage_init("sort live count", &u32_bytes(&[live as u32]));
        let mut encoder = ctx.encoder("sort");
        let mut keep = Vec::new();
        let sort = SortKeys {
            keys: &buf,
            n_sort: keys.len() as u64,
            count: &count,
            count_word: 0,
            n_tiles,
            label: "keys",
        };
        self.encode_sort_in(&mut encoder, &sort, &mut keep, None)?;
        // The buffer holds at least one key's bytes, even for no keys.
        let back = ctx.read_back(encoder, &[(&buf, keys.len().max(1) as u64 * 16)])?;
        Ok(bytes_u32(&back[0])
            .chunks_exact(4)
            .take(keys.len())
            .map(|k| [k[0], k[1], k[2], k[3]])
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_digits_cover_the_order_bits_then_the_tile_bits() {
        let order: Vec<(u32, u32)> = (0..8).map(|d| (1, 4 * d)).collect();
        assert_eq!(radix_digits(0), order);
        assert_eq!(radix_digits(1), order);
        // (tiles, tile digits): 2..=16 tiles need 1 to 4 bits, 17 need 5.
        for (n_tiles, tile_digits) in [(2, 1), (16, 1), (17, 2), (4096, 3), (4097, 4)] {
            let digits = radix_digits(n_tiles);
            assert_eq!(digits[..8], order[..], "{n_tiles} tiles");
            let tile: Vec<(u32, u32)> = (0..tile_digits).map(|d| (0, 4 * d)).collect();
            assert_eq!(digits[8..], tile[..], "{n_tiles} tiles");
        }
        assert_eq!(radix_digits(u32::MAX).len(), 16);
    }
}
