"""`repaint-nerf bench compare`: the same benchmarks on two checkouts (a base, e.g. main, and a change), one
after the other in one run, and the ratio of every figure (head / base).

Run it before a change to the field, the renderer, the trainer or the selection lands. Each side runs in its
own process with this interpreter and that checkout's code (a git ref is checked out into a temporary
worktree), alternating base and head per repetition (A B, then B A) so a machine that drifts during the run
weighs on both. Two cores give no clean figure to two jobs at once: it warns when the machine is busy.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

HELP = "run benchmarks on two checkouts (base ref vs a change) side by side and print each figure's ratio"
BENCHES = ("recon", "viewport", "scale")
DEFAULT_ARGS = {
    "recon": "--seconds 90",
    "viewport": "",
    "scale": "--sizes 128,256,512 --seconds 300",
}
PACKAGE_FOLDERS = ("core", "app", "shaders", "assets")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--base", default="main", help="git ref or checkout folder to compare against (default: main)")
    p.add_argument("--head", default=".", help="git ref or checkout folder of the change (default: this working "
                                                "tree, uncommitted edits included)")
    p.add_argument("--benches", default="recon,viewport,scale", help=f"which of {', '.join(BENCHES)}")
    for name in BENCHES:
        p.add_argument(f"--{name}-args", default=DEFAULT_ARGS[name],
                       help=f"arguments for `bench {name}` on both sides (default: {DEFAULT_ARGS[name]!r})")
    p.add_argument("--repeats", type=int, default=1, help="runs per side and benchmark (alternating order)")
    p.add_argument("--out", default="bench-compare", help="folder for each run's JSON and the summary")


def _git(*args: str, cwd: Path) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def _checkout(spec: str, scratch: Path) -> tuple[Path, str]:
    """(folder, description) of a checkout: a folder as it is, or a git ref in a detached temporary worktree."""
    from repaint_nerf.core.errors import UserError

    folder = Path(spec)
    if folder.is_dir() and (folder / "core").is_dir():
        return folder.resolve(), f"{folder.resolve()} (working tree)"
    repo = Path(__file__).resolve().parents[2]
    try:
        sha = _git("rev-parse", "--verify", f"{spec}^{{commit}}", cwd=repo)
    except (subprocess.CalledProcessError, FileNotFoundError):
        raise UserError(f"{spec!r} is neither a checkout folder nor a git ref of {repo}",
                        hint="give a branch, tag, commit or a folder holding core/ and app/") from None
    dest = scratch / sha[:12]
    if not dest.is_dir():
        _git("worktree", "add", "--detach", "--force", str(dest), sha, cwd=repo)
    return dest, f"{spec} ({sha[:12]})"


def command_for(folder: Path, scratch: Path) -> tuple[list[str], dict]:
    """The command prefix and environment that run `repaint-nerf` from a checkout with this interpreter: a
    package folder linking its core/, app/, ... as repaint_nerf.* first on the path (builds before the
    repaint_nerf package name imported them as top-level core and app)."""
    import repaint_nerf.core as core

    env = dict(os.environ)
    if not core.THP_FROM_USER:  # each checkout sets (or not) its own allocator settings
        env.pop(core.THP_ENV, None)
    if "repaint_nerf" in (folder / "app" / "cli.py").read_text(encoding="utf-8"):
        shim = scratch / f"shim-{abs(hash(str(folder)))}" / "repaint_nerf"
        shim.mkdir(parents=True, exist_ok=True)
        (shim / "__init__.py").touch()
        for name in PACKAGE_FOLDERS:
            link = shim / name
            if not link.exists() and (folder / name).is_dir():
                link.symlink_to(folder / name, target_is_directory=True)
        root, module = shim.parent, "repaint_nerf.app.cli"
    else:
        root, module = folder, "app.cli"
    env["PYTHONPATH"] = os.pathsep.join([str(root)] + [p for p in [env.get("PYTHONPATH")] if p])
    return [sys.executable, "-m", module], env


def _busy() -> str | None:
    """A warning when another process keeps the CPU busy (load over a third of a core)."""
    try:
        load = os.getloadavg()[0]
    except OSError:
        return None
    return f"the machine is busy (1-minute load {load:.2f}): figures side by side are only fair on an idle one" \
        if load > 0.35 else None


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.errors import UserError

    benches = [b.strip() for b in args.benches.split(",") if b.strip()]
    unknown = [b for b in benches if b not in BENCHES]
    if unknown or not benches:
        raise UserError(f"unknown benchmark(s) {', '.join(unknown) or '(none)'}", hint=f"choose from {', '.join(BENCHES)}")
    if args.repeats < 1:
        raise UserError(f"--repeats must be at least 1, got {args.repeats}")
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if (warning := _busy()) is not None:
        print(f"warning: {warning}", flush=True)
    scratch = Path(tempfile.mkdtemp(prefix="repaint-nerf-compare-"))
    try:
        return _run_sides(args, benches, out, scratch)
    finally:
        _remove_worktrees(scratch)


def _remove_worktrees(scratch: Path) -> None:
    """Drop the temporary worktrees `_checkout` added (and their git bookkeeping), then the scratch folder."""
    import shutil

    repo = Path(__file__).resolve().parents[2]
    for child in scratch.iterdir():
        if (child / ".git").is_file():
            subprocess.run(["git", "worktree", "remove", "--force", str(child)], cwd=repo, capture_output=True)
    shutil.rmtree(scratch, ignore_errors=True)


def _run_sides(args: argparse.Namespace, benches: list[str], out: Path, scratch: Path) -> int:
    """Run every benchmark on both sides, alternating, and print and save the ratios."""
    from repaint_nerf.core.bench.compare import compare, format_rows
    from repaint_nerf.core.workspace import atomic

    sides = {}
    for side, spec in (("base", args.base), ("head", args.head)):
        folder, desc = _checkout(spec, scratch)
        sides[side] = (folder, desc, *command_for(folder, scratch))
        print(f"{side}: {desc}", flush=True)
    summary: dict = {"base": sides["base"][1], "head": sides["head"][1], "benches": {}}
    for bench in benches:
        results: dict[str, list[dict]] = {"base": [], "head": []}
        for rep in range(args.repeats):
            for side in (("base", "head") if rep % 2 == 0 else ("head", "base")):
                folder, desc, cmd, env = sides[side]
                path = out / f"{bench}_{side}_{rep}.json"
                argv = cmd + ["bench", bench, *shlex.split(getattr(args, f"{bench}_args")), "--json", str(path)]
                print(f"[{bench} {side} {rep + 1}/{args.repeats}] {' '.join(argv[1:])}", flush=True)
                with open(out / f"{bench}_{side}_{rep}.log", "w") as log:
                    rc = subprocess.run(argv, cwd=folder, env=env, stdout=log, stderr=subprocess.STDOUT).returncode
                if rc == 0 and path.is_file():
                    results[side].append(json.loads(path.read_text()))
                else:
                    print(f"  {side} failed (exit {rc}): see {out / f'{bench}_{side}_{rep}.log'}", flush=True)
        rows = [compare(bench, b, h) for b, h in zip(results["base"] or [None], results["head"] or [None])]
        summary["benches"][bench] = rows
        for k, r in enumerate(rows):
            print(format_rows(bench if len(rows) == 1 else f"{bench} (run {k + 1})", r), flush=True)
    atomic.write_json(out / "compare.json", summary)
    print(f"wrote {out / 'compare.json'}")
    return 0
