//! The straightforward kernels of `shaders/ssim_topk.wgsl` (one workgroup per pair; one
//! invocation per query folding a tile sequentially), kept as device references: tests hold the
//! block-tiled kernel and the parallel top-K to them on the same device, and feed `topk_merge`
//! scores no SSIM produces (NaN). The coarse executor does not use them, and contexts do not build
//! them: each call here builds its pipeline (`kernels::reference_kernels`).

use crate::device::context::{GpuContext, GpuError};
use semlook_kernels::abi::{SsimParams, TileParams, MAX_ROW_SUMS};

/// `ssim_tile` on every (query, reference) pair of one tile: scores query-major.
pub fn ssim_tile_scores(ctx: &GpuContext, p: &SsimParams, queries: (&[f32], &[f32]), refs: (&[f32], &[f32])) -> Result<Vec<f32>, GpuError> {
    let (nq, nr) = (queries.0.len() / p.len(), refs.0.len() / p.len());
    let rows = (p.gh * p.nw) as usize;
    if rows > MAX_ROW_SUMS || nr > ctx.max_workgroups() as usize || nq > ctx.max_workgroups() as usize {
        return Err(GpuError::LimitsTooSmall {
            adapter: ctx.describe(),
            what: "ssim_tile's row sums or workgroups".into(),
            needed: rows.max(nr).max(nq) as u64,
            available: MAX_ROW_SUMS as u64,
        });
    }
    let tp = TileParams { queries: nq as u32, tile_len: nr as u32, tile_start: 0, k: 1 };
    ctx.scoped("scoring a tile with ssim_tile", || -> Result<Vec<f32>, GpuError> {
        let upload = |label: &str, data: &[f32]| {
            let b = ctx.storage(label, (data.len() * 4) as u64);
            ctx.write(&b, 0, bytemuck::cast_slice(data));
            b
        };
        let (qg, qs, rg, rs) = (upload("queries", queries.0), upload("query stats", queries.1), upload("tile", refs.0), upload("tile stats", refs.1));
        let scores = ctx.storage("scores", (nq * nr * 4) as u64);
        let (pb, tpb) = (ctx.uniform("ssim params", p), ctx.uniform("tile params", &tp));
        let (ssim_tile, _) = crate::device::kernels::reference_kernels(&ctx.device, ctx.uses_subgroups())?;
        let g = ssim_tile.bind(&ctx.device, &[&pb, &tpb, &qg, &qs, &rg, &rs, &scores]);
        ctx.run("ssim tile", &[(&ssim_tile.pipeline, &g, [nr as u32, nq as u32, 1])])?;
        ctx.read_back_values(&scores, nq * nr)
    })?
}

/// Runs the `topk_merge` kernel alone: folds `scores` (tile scores, query-major) into the K-lists
/// `top_s` / `top_i` (queries x k, best first) and reads them back. It lets tests feed the
/// kernel scores no SSIM produces (NaN) and compare with its twin `ssim_topk::topk_merge`.
pub fn merge_scores(ctx: &GpuContext, tp: &TileParams, scores: &[f32], top_s: &[f32], top_i: &[u32]) -> Result<(Vec<f32>, Vec<u32>), GpuError> {
    let n = tp.queries as usize * tp.k as usize;
    ctx.scoped("merging scores", || -> Result<(Vec<f32>, Vec<u32>), GpuError> {
        let upload = |label: &str, data: &[u8]| {
            let b = ctx.storage(label, data.len() as u64);
            ctx.write(&b, 0, data);
            b
        };
        let (sb, tsb, tib) = (
            upload("scores", bytemuck::cast_slice(scores)),
            upload("top-k scores", bytemuck::cast_slice(&top_s[..n])),
            upload("top-k indices", bytemuck::cast_slice(&top_i[..n])),
        );
        let tpb = ctx.uniform("tile params", tp);
        let (_, topk_merge) = crate::device::kernels::reference_kernels(&ctx.device, ctx.uses_subgroups())?;
        let g = topk_merge.bind(&ctx.device, &[&tpb, &sb, &tsb, &tib]);
        ctx.run("topk merge", &[(&topk_merge.pipeline, &g, [tp.queries.div_ceil(64), 1, 1])])?;
        Ok((ctx.read_back_values(&tsb, n)?, ctx.read_back_values(&tib, n)?))
    })?
}

/// The parallel top-K kernels alone (`topk_partial`, `topk_merge_lists`) on given scores
/// (queries x n, query-major), in passes of `pass` references: the device side of
/// `topk_select`'s twin, fed scores no SSIM produces (NaN, infinities, exact ties).
pub fn select_topk(ctx: &GpuContext, scores: &[f32], nq: usize, k: usize, pass: usize) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
    use super::topk::{TopK, MAX_PASS_REFS};
    use crate::device::buffers::{PassBuffer, Reused};
    use semlook_kernels::abi::PassParams;
    use semlook_kernels::topk_select::SEG;
    let n = scores.len() / nq.max(1);
    let pass = pass.clamp(1, MAX_PASS_REFS);
    let starts: Vec<usize> = (0..n).step_by(pass).collect();
    let entries: Vec<PassParams> = starts
        .iter()
        .enumerate()
        .map(|(i, &s)| {
            let refs = pass.min(n - s);
            PassParams {
                queries: nq as u32,
                refs: refs as u32,
                ref_index: s as u32,
                k: k as u32,
                segs: refs.div_ceil(SEG) as u32,
                parity: (i % 2) as u32,
                fresh: (i == 0) as u32,
                ..Default::default()
            }
        })
        .collect();
    let (mut topk, mut passes, mut block) = (TopK::default(), PassBuffer::new(ctx), Reused::default());
    ctx.scoped("selecting top-k lists", || -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        let pbuf = passes.write(ctx, &entries);
        let sbuf = block.get(ctx, "scores", (nq * pass * 4) as u64).clone();
        let group = topk.begin(ctx, nq, k, pass, pbuf, &sbuf);
        for (i, ps) in entries.iter().enumerate() {
            let s = starts[i];
            let rows: Vec<f32> = (0..nq).flat_map(|q| scores[q * n + s..q * n + s + ps.refs as usize].iter().copied()).collect();
            ctx.write(&sbuf, 0, bytemuck::cast_slice(&rows));
            let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("top-k pass") });
            {
                let mut cp = ctx.begin_pass(&mut enc, "top-k pass")?;
                TopK::record(ctx, &mut cp, &group, passes.offset(i), ps);
            }
            ctx.queue.submit([enc.finish()]);
        }
        topk.read(ctx, nq, k, (entries.len() % 2) as u32)
    })?
}
