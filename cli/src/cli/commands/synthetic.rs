//! `synth`: the synthetic benchmark, its CamVid copies and its streams.

use super::*;

pub(super) fn synth_config(a: &SynthArgs) -> SynthConfig {
    let mut c = SynthConfig {
        seed: a.seed,
        places: a.places,
        width: a.size.0,
        height: a.size.1,
        reference: a.reference,
        aliasing: a.aliasing,
        ..Default::default()
    };
    if !a.queries.is_empty() {
        c.queries = a.queries.clone();
    }
    c
}

/// `synth --from-camvid`: the real-label benchmark, and with --evaluate its two evaluations.
pub(super) fn camvid_cmd(camvid: &Path, a: &SynthArgs, engine: &dyn Fn() -> Result<Engine>, quiet: bool) -> Result<()> {
    use semlook_cli::tools::synth::camvid::{self, Change};
    let changes = if a.changes.is_empty() { Change::ALL.to_vec() } else { a.changes.clone() };
    let t = Instant::now();
    let pb = progress::bar(0, "frames", quiet);
    let n = camvid::generate(camvid, &a.out, &changes, a.step, &|| pb.inc(1))?;
    pb.finish_and_clear();
    info(quiet, format!("wrote {n} frames x {} traversals to {} in {:.1} s", 1 + changes.len(), a.out.display(), t.elapsed().as_secs_f64()));
    if !a.evaluate {
        return Ok(());
    }
    let cfg = apply_models(Config::camvid(), &a.models);
    let ds = Dataset::open(&a.out, &DatasetOptions::default())?;
    let mut engine = engine()?;
    let opts = EvalOptions { settings: Setting::ALL.to_vec(), map: None, skip_invalid: false, quiet, sequence: false, label_cache: None };
    info(quiet, "evaluating with the real labels");
    let real = evaluate(&ds, &cfg, &opts, &mut engine)?;
    info(quiet, "evaluating with the segmenter's labels");
    let seg = evaluate(&ds.without_labels(), &cfg, &opts, &mut engine)?;
    write_file(&a.out.join("eval-real-labels.json"), &to_json(&real)?)?;
    write_file(&a.out.join("eval-segmenter-labels.json"), &to_json(&seg)?)?;
    out!("{}", semlook::eval::label_source_table(&[("real labels", &real), ("segmenter labels", &seg)]));
    out!("\nsegmenter run:\n{}", seg.run.describe());
    Ok(())
}

/// `synth --stream-from`: a dataset's query traversals driven again at varying speed, with stops.
pub(super) fn stream_synth_cmd(dir: &Path, a: &SynthArgs, quiet: bool) -> Result<()> {
    use semlook_cli::tools::synth::stream::{write, StreamProfile};
    let ds = Dataset::open(dir, &DatasetOptions::default())?;
    let p = StreamProfile { speed_min: a.speed_min, speed_max: a.speed_max, stops: a.stops, stop_frames: a.stop_frames, seed: a.seed };
    let n = write(&ds, &a.out, &p)?;
    info(quiet, format!("wrote {} ({} query frames over {} traversals)", a.out.join(semlook::dataset::MANIFEST).display(), n, ds.queries.len()));
    Ok(())
}

pub(super) fn synth_cmd(a: &SynthArgs, quiet: bool) -> Result<()> {
    let cfg = synth_config(a);
    cfg.validate()?;
    let t = Instant::now();
    let pb = progress::bar(cfg.places * (1 + cfg.queries.len()), "rendering", quiet);
    synth::generate(&cfg, &a.out, &|| pb.inc(1))?;
    pb.finish_and_clear();
    info(quiet, format!("wrote {} frames to {} in {:.1} s", cfg.places * (1 + cfg.queries.len()), a.out.display(), t.elapsed().as_secs_f64()));
    Ok(())
}
