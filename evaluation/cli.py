"""``python -m evaluation {run,preset,generate,subset,summarize}``: the experiment runner's command line.

Without ``--gateway`` the runner starts the whole system itself (zenoh router and every service, via
:class:`deploy.launcher.Launcher`, logs under ``<out>/system``; with ``--robots N`` a robot-io and a
gateway per robot and the other services shared) and stops it at the end; with
``--gateway URL`` it uses a running one (scenes are switched through the gateway's ``POST /robot/scene``).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from evaluation.clouds import CURATED_DENSITY_PER_M2
from evaluation.errors import ConfigError, EvaluationError
from evaluation.gateway_client import GatewayClient
from evaluation.results import COLUMNS, ResultsLog, markdown_table, summary_row, write_tables
from evaluation.runner import RESULTS_FILE, EvalRunner, Lane, SceneMapIndex, MapSource, RunConfig

log = logging.getLogger("evaluation")


def _system_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("system")
    g.add_argument("--gateway", action="append",
                   help="use a running gateway at this URL (default: start the system); repeat it for more "
                        "robots (one gateway per robot, on any host): scenes are sharded over them")
    g.add_argument("--robots", type=int, default=1,
                   help="without --gateway: start robot0..robotN-1 (a robot-io and a gateway each, the other "
                        "services shared) and shard the scenes over them")
    g.add_argument("--replica", action="append", metavar="SERVICE=N",
                   help="without --gateway: run N replicas of a shared service (planner, mapper, renderer); "
                        "planner and mapper replicas split the robots between them")
    g.add_argument("--token", help="the gateway's API token (ANT_API_TOKEN)")
    g.add_argument("--robot", default="robot0", help="robot id of the key expressions")
    g.add_argument("--start-timeout-s", type=float, default=120.0, help="deadline for the system to come up")


def _run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--episodes", required=True, type=Path, help="R2R-CE / RxR-CE episode file (.json.gz)")
    p.add_argument("--gt", type=Path, help="ground-truth file (default: <episodes>_gt.json.gz when it exists)")
    p.add_argument("--policy", default="heuristic")
    p.add_argument("--policy-config", type=json.loads, default={}, help="JSON object")
    p.add_argument("--limit", type=int)
    p.add_argument("--subset", help="run exactly a subset's episodes: a file written by `subset`, or a published "
                                    "name (evaluation/subsets/<name>.json); refused when the file lacks them")
    p.add_argument("--scenes-dir", type=Path, help="where mesh scene ids (mp3d/X/X.glb) are looked up")
    p.add_argument("--map-source", choices=[m.value for m in MapSource], default=MapSource.RECONSTRUCTED.value)
    p.add_argument("--max-steps", type=int, default=40)
    p.add_argument("--no-anticipation", action="store_true")
    p.add_argument("--hfov-deg", type=float, default=90.0, help="anticipated-view HFOV")
    p.add_argument("--splat-mode", choices=["paper", "visibility"], help="renderer splat mode of anticipated views")
    p.add_argument("--anticipation-views", choices=["map", "true-scene"], default="map",
                   help="true-scene: ray-cast from the simulator's scene (a control)")
    p.add_argument("--no-spatial-map", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reference", choices=["auto", "gt", "episode"], default="auto", help="nDTW reference path")
    p.add_argument("--mission-timeout-s", type=float, default=1800.0)
    p.add_argument("--exploration-timeout-s", type=float, default=7200.0)
    p.add_argument("--exploration-max-steps", type=int, default=400)
    p.add_argument("--maps", type=Path, help="map-id cache shared between runs (default: <out>/maps.json)")
    p.add_argument("--curated-density-per-m2", type=float, default=CURATED_DENSITY_PER_M2,
                   help="points per m2 of visible surface in a curated cloud (--map-source curated); the "
                        "default is what the paper's curated row needs, a sparser one builds, uploads and "
                        "indexes faster (the suite's runs, which test the runner's path, not its maps)")
    p.add_argument("--no-retry-errors", action="store_true", help="on resume, keep episodes that errored")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--record", action="store_true", help="record every mission (.rrd) into <out>/recordings/")
    p.add_argument("--no-plots", action="store_true",
                   help="draw no top-down plot per episode (<out>/plots/, about 0.1 s of CPU each); summary.md says "
                        "plots off. Not a setting of the experiment: a resumed run may switch it")
    g = p.add_argument_group("cost")
    g.add_argument("--prices", type=Path, help="price table (JSON or TOML: model -> input_per_1m_usd, "
                                               "output_per_1m_usd) over the defaults of shared/pricing.py")
    g.add_argument("--budget-usd", type=float,
                   help="stop the run once it has spent this many dollars: every attempt logged in <out>, the "
                        "missions in flight included; those are cancelled and run again on resume")
    g.add_argument("--budget-tokens", type=int, help="the same for LLM tokens (prompt + completion)")
    g.add_argument("--budget-wall-s", type=float, help="stop the run after this many seconds (of this call)")
    g.add_argument("--estimate", action="store_true",
                   help="print the run's expected tokens and dollars from the prompt sizes, call nothing, exit")
    g.add_argument("--estimate-waypoints", type=int, default=4, help="waypoints per step the estimate assumes")
    g.add_argument("--estimate-step-m", type=float, default=2.0, help="metres per step the estimate assumes")
    g.add_argument("--estimate-completion-tokens", type=int, default=60, help="answer tokens per call")
    _system_args(p)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m evaluation", description=__doc__.split("\n")[0])
    ap.add_argument("-v", "--verbose", action="store_true")
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run an episode file through the system (resumable)")
    _run_args(run)
    run.add_argument("--out", type=Path, default=Path("runs/eval/run"))
    pre = sub.add_parser("preset", help="run one of the paper's comparisons (cloud, anticipation, hfov, "
                                        "policies, all)")
    pre.add_argument("name")
    _run_args(pre)
    pre.add_argument("--out", type=Path, default=Path("runs/eval/presets"))
    pre.add_argument("--chunk", type=int, help="variants take turns, this many more episodes each per round")
    gen = sub.add_parser("generate", help="write the generated evaluation set (R2R-CE format)")
    gen.add_argument("--out", type=Path, required=True)
    gen.add_argument("--houses", type=int, default=5)
    gen.add_argument("--per-house", type=int, default=20)
    gen.add_argument("--floors", default="1,2", help="floors per house, cycled (e.g. 1,2)")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--area-m2", type=float)
    gen.add_argument("--no-gt", action="store_true", help="skip the *_gt.json.gz ground-truth file")
    sset = sub.add_parser("subset", help="draw a deterministic subset (episode ids, seed, source sha256) from "
                                         "an episode file")
    sset.add_argument("--episodes", "--dataset", dest="episodes", type=Path, required=True,
                      help="R2R-CE / RxR-CE episode file (.json.gz)")
    sset.add_argument("--preset", help="a published rule (count, seed, strata, languages): "
                                       "r2r-ce-val-unseen-100, rxr-ce-val-unseen-195, rxr-ce-val-unseen-195-en")
    sset.add_argument("--count", type=int)
    sset.add_argument("--seed", type=int)
    sset.add_argument("--by", help="strata, comma-separated: scene, language (default: scene, plus language "
                                   "when the episodes have one)")
    sset.add_argument("--languages", help="keep these instruction languages (prefixes: 'en' = en-US, en-IN)")
    sset.add_argument("--name", help="the subset's name (default: the preset's, or from the file name)")
    sset.add_argument("--out", type=Path, required=True, help="the subset file (.json)")
    summ = sub.add_parser("summarize", help="print (and rewrite) the summary of result folders")
    summ.add_argument("dirs", nargs="+", type=Path)
    summ.add_argument("--out", type=Path, help="also write the combined table to <out>.md / .csv")
    return ap


def _model(a: argparse.Namespace) -> str:
    from services.planner.core.openai_policy import OpenAIConfig

    return str(a.policy_config.get("model") or OpenAIConfig.model_fields["model"].default)


def _prices(a: argparse.Namespace):
    from shared.pricing import PriceTable, PriceTableError

    try:
        return PriceTable.load(a.prices)
    except PriceTableError as exc:
        raise ConfigError(str(exc)) from None


def _policy_config(a: argparse.Namespace) -> dict:
    """The policy config, with the price table's prices for the openai model when --prices is given (so
    the planner prices calls as the estimate does; explicit prices in --policy-config win)."""
    cfg = dict(a.policy_config)
    if a.prices and a.policy == "openai":
        price = _prices(a).lookup(_model(a))
        if price is None:
            raise ConfigError(f"{a.prices}: no price for model {_model(a)!r}")
        cfg.setdefault("price_input_per_1m_usd", price.input_per_1m_usd)
        cfg.setdefault("price_output_per_1m_usd", price.output_per_1m_usd)
    return cfg


def run_config(a: argparse.Namespace) -> RunConfig:
    from pydantic import ValidationError

    try:
        return _run_config(a)
    except ValidationError as exc:  # a bad option value (a budget <= 0, say) is the user's error, in words
        raise ConfigError("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())) from None


def _run_config(a: argparse.Namespace) -> RunConfig:
    return RunConfig(
        policy=a.policy, policy_config=_policy_config(a), budget_usd=a.budget_usd, budget_tokens=a.budget_tokens,
        budget_wall_s=a.budget_wall_s, max_steps=a.max_steps, anticipation=not a.no_anticipation,
        anticipation_hfov_deg=a.hfov_deg, spatial_map=not a.no_spatial_map, map_source=MapSource(a.map_source),
        seed=a.seed, reference=a.reference, limit=a.limit, scenes_dir=a.scenes_dir,
        curated_density_per_m2=a.curated_density_per_m2,
        mission_timeout_s=a.mission_timeout_s, exploration_timeout_s=a.exploration_timeout_s,
        exploration_max_steps=a.exploration_max_steps, retry_errors=not a.no_retry_errors, record=a.record,
        plots=not a.no_plots,
        anticipation_splat_mode=a.splat_mode, anticipation_views=a.anticipation_views)


def load_episodes(a: argparse.Namespace):
    from evaluation.dataset import gt_path_for
    from libs.world import read_episodes, read_ground_truth

    ds = read_episodes(a.episodes)
    if getattr(a, "subset", None):
        from evaluation.dataset import Subset

        subset = Subset.read(a.subset)
        ds.episodes = subset.apply(ds.episodes, a.episodes)
        log.info("subset %s: %d episodes (seed %d, drawn from %s)", subset.name, len(ds.episodes),
                 subset.rule.seed, subset.source_name)
    gt_path = a.gt or gt_path_for(a.episodes)
    gt = read_ground_truth(gt_path) if gt_path.is_file() else None
    if a.gt and gt is None:
        raise ConfigError(f"ground-truth file not found: {a.gt}")
    log.info("%d episodes from %s%s", len(ds.episodes), a.episodes, f", ground truth {gt_path}" if gt else "")
    return ds.episodes, gt


@contextmanager
def system(a: argparse.Namespace, out: Path) -> Iterator[list[Lane]]:
    """One lane (gateway client and scene switcher) per robot: running systems', or systems started for
    this run (one per robot, robot ids robot0..robotN-1, logs under ``<out>/system[-robotK]``)."""
    with ExitStack() as stack:
        if a.gateway and a.robots != 1:
            raise ConfigError("--robots starts systems; with --gateway, give one --gateway per robot instead")
        if a.gateway:
            # The gateway switches robot-io's scene too (POST /robot/scene): HTTP is all a run needs.
            gateways = [stack.enter_context(GatewayClient.connect(url, token=a.token)) for url in a.gateway]
            yield [Lane(g, g) for g in gateways]
            return
        from deploy.launcher import Launcher

        if a.robots < 1:
            raise ConfigError(f"--robots must be >= 1, got {a.robots}")
        replicas = _replicas(a.replica or [])
        run_dir = out / "system"
        log.info("starting the system: %d robot(s), shared services %s (logs in %s)", a.robots,
                 replicas or "x1", run_dir)
        env = {}
        if a.scenes_dir:  # robot-io loads scene files only from its configured directories (issue 15)
            env["ANT_SCENE_DIRS"] = json.dumps([str(a.scenes_dir.resolve())])
        # One system: robot-io and a light gateway per robot (robot0..robotN-1), the planner, mapper,
        # renderer and reconstructor shared by all robots (deploy.launcher.PER_ROBOT).
        launcher = Launcher(run_dir, extra_env=env, robots=a.robots, replicas=replicas)
        stack.callback(launcher.stop)
        t0 = time.monotonic()
        launcher.start(a.start_timeout_s)
        log.info("system up in %.1f s, gateways %s", time.monotonic() - t0, ", ".join(launcher.gateway_urls))
        lanes = []
        for url in launcher.gateway_urls:
            gateway = stack.enter_context(GatewayClient.connect(url, token=a.token))
            lanes.append(Lane(gateway, gateway))
        yield lanes


def _replicas(specs: list[str]) -> dict[str, int]:
    out: dict[str, int] = {}
    for spec in specs:
        name, _, count = spec.partition("=")
        if name not in ("planner", "mapper", "renderer") or not count.isdigit() or not 1 <= int(count) <= 16:
            raise ConfigError(f"--replica {spec!r}: want planner|mapper|renderer=<1..16>")
        out[name] = int(count)
    return out


def cmd_estimate(a: argparse.Namespace, episodes) -> int:
    from evaluation.ledger import estimate_run

    selected = episodes[: a.limit] if a.limit else episodes
    est = estimate_run(selected, model=_model(a), prices=_prices(a), max_steps=a.max_steps,
                       anticipation=not a.no_anticipation, spatial_map=not a.no_spatial_map,
                       waypoints=a.estimate_waypoints, step_m=a.estimate_step_m,
                       completion_tokens_per_call=a.estimate_completion_tokens,
                       detail=str(a.policy_config.get("image_detail", "auto")), policy_config=a.policy_config)
    if a.policy != "openai":
        print(f"policy {a.policy} makes no LLM calls (it costs $0); as openai:{est.model} the run would cost:")
    print("\n".join(est.lines()))
    if a.budget_usd is not None:
        print(f"  budget            {a.budget_usd:>12.2f}  ({'enough' if est.cost_usd <= a.budget_usd else 'short'})")
    if a.budget_tokens is not None:
        tokens = est.prompt_tokens + est.completion_tokens
        print(f"  token budget      {a.budget_tokens:>12,d}  ({'enough' if tokens <= a.budget_tokens else 'short'})")
    return 0


def cmd_run(a: argparse.Namespace) -> int:
    episodes, gt = load_episodes(a)
    if a.estimate:
        return cmd_estimate(a, episodes)
    cfg = run_config(a)
    t0 = time.monotonic()
    with system(a, a.out) as lanes:
        cache = SceneMapIndex(a.maps or a.out / "maps.json")
        label = f"{cfg.policy}/{cfg.map_source.value}"
        report = EvalRunner(lanes[0].gateway, lanes[0].scenes, cfg, a.out, map_cache=cache, label=label,
                            progress=not a.no_progress, lanes=lanes[1:]).run(episodes, gt)
    print(markdown_table([report.row]))
    print(f"{report.ran} episodes run, {report.resumed} resumed; results in {a.out / RESULTS_FILE}; "
          f"wall time {time.monotonic() - t0:.0f} s")
    print(f"spent by the run (every attempt): ${report.spent.usd:.4f}, {report.spent.tokens:,d} tokens")
    if report.stopped:
        print(f"stopped early: {report.stopped}")
    return 0


def cmd_preset(a: argparse.Namespace) -> int:
    from evaluation.presets import presets, run_preset

    names = list(presets()) if a.name == "all" else [a.name]
    unknown = [n for n in names if n not in presets()]
    if unknown:
        raise ConfigError(f"unknown preset {unknown[0]!r}; known: {', '.join(presets())}, all")
    episodes, gt = load_episodes(a)
    base = run_config(a)
    t0 = time.monotonic()
    with system(a, a.out) as lanes:
        gateway, scenes = lanes[0].gateway, lanes[0].scenes
        cache = SceneMapIndex(a.maps or a.out / "maps.json")
        for name in names:
            rep = run_preset(name, episodes, gt, base, a.out, gateway, scenes, map_cache=cache,
                             progress=not a.no_progress, lanes=lanes[1:], chunk=a.chunk)
            print(f"\n## {rep.preset.title}\n")
            print(markdown_table(rep.rows))
            print(f"{rep.preset.paper}\ntable {rep.table_md}, plot {rep.plot_png}")
    print(f"wall time {time.monotonic() - t0:.0f} s")
    return 0


def cmd_generate(a: argparse.Namespace) -> int:
    from evaluation.dataset import SetSpec, generate_set, parse_floors, write_set

    spec = SetSpec(houses=a.houses, per_house=a.per_house, floors=parse_floors(a.floors), seed=a.seed,
                   area_m2=a.area_m2)
    t0 = time.monotonic()
    ds, gt = generate_set(spec, with_gt=not a.no_gt,
                          progress=lambda i, n, s: print(f"[{i + 1}/{n}] {s}", file=sys.stderr))
    paths = write_set(ds, gt, a.out)
    print(f"{len(ds.episodes)} episodes over {spec.houses} houses -> {', '.join(map(str, paths))} "
          f"({time.monotonic() - t0:.0f} s)")
    return 0


def cmd_subset(a: argparse.Namespace) -> int:
    from dataclasses import replace

    from evaluation.dataset import SUBSET_PRESETS, SubsetRule, episode_language, make_subset
    from libs.world import read_episodes

    if a.preset and a.preset not in SUBSET_PRESETS:
        raise ConfigError(f"unknown subset preset {a.preset!r}; known: {', '.join(SUBSET_PRESETS)}")
    if not a.preset and a.count is None:
        raise ConfigError("give --count (or --preset)")
    rule = SUBSET_PRESETS[a.preset] if a.preset else None
    if a.by:
        strata = tuple(s.strip() for s in a.by.split(",") if s.strip())
    elif rule:
        strata = rule.strata
    else:  # RxR-CE: languages are strata too, so each language keeps its share
        has_lang = any(episode_language(e) for e in read_episodes(a.episodes).episodes)
        strata = ("scene", "language") if has_lang else ("scene",)
    languages = tuple(x.strip() for x in a.languages.split(",") if x.strip()) if a.languages else None
    rule = replace(rule, strata=strata) if rule else SubsetRule(count=a.count, strata=strata)
    rule = replace(rule, count=a.count if a.count is not None else rule.count,
                   seed=a.seed if a.seed is not None else rule.seed,
                   languages=languages if languages is not None else rule.languages)
    subset = make_subset(a.episodes, rule, name=a.name or a.preset)
    subset.write(a.out)
    langs = f", languages {subset.languages}" if subset.languages else ""
    print(f"{subset.name}: {len(subset.episode_ids)} of {subset.source_episodes} episodes, {len(subset.scenes)} "
          f"scenes{langs}, seed {rule.seed}, source sha256 {subset.source_sha256} -> {a.out}")
    return 0


def cmd_summarize(a: argparse.Namespace) -> int:
    rows = []
    for d in a.dirs:
        results = list(ResultsLog(d / RESULTS_FILE).load().values())
        if not results:
            raise ConfigError(f"{d}: no {RESULTS_FILE}")
        rows.append(summary_row(results, d.name))
    print(markdown_table(rows))
    if a.out:
        write_tables(rows, a.out, COLUMNS)
    return 0


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    from shared.logs import configure_logging

    configure_logging("evaluation", "cli", "DEBUG" if a.verbose else "INFO", False)
    # Request lines of the HTTP client would drown the progress bar.
    for noisy in ("httpx", "httpx2", "httpcore"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    try:
        return {"run": cmd_run, "preset": cmd_preset, "generate": cmd_generate, "summarize": cmd_summarize,
                "subset": cmd_subset}[
            a.command](a)
    except (EvaluationError, FileNotFoundError) as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt as exc:  # Ctrl-C; SIGTERM and SIGHUP too while a system runs (deploy.launcher.Stopped)
        log.warning("interrupted (%s): finished episodes are saved; run the same command again to resume",
                    exc or "SIGINT")
        return getattr(exc, "exit_code", 130)
