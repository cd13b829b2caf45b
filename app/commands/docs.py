"""`repaint-nerf docs`: regenerate docs/BENCHMARKS.md and the README's figure table from the benches' JSON."""
from __future__ import annotations

import argparse
from pathlib import Path

NAME = "docs"
HELP = "regenerate docs/BENCHMARKS.md and the README's figure table from the bench JSON in docs/bench/"
BEGIN, END = "<!-- figures:begin -->", "<!-- figures:end -->"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bench-dir", default="docs/bench", help="folder of the bench JSON files (default docs/bench)")
    p.add_argument("--readme", default="README.md", help=f"README whose table between {BEGIN} and {END} is replaced")
    p.add_argument("--out", default="docs/BENCHMARKS.md", help="the benchmarks page to write")
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 when either file is out of date")


def render(bench_dir: Path, readme: str, readme_dir: Path, out: Path) -> tuple[str, str]:
    """(the README's new text, the benchmarks page) from the JSON in `bench_dir`."""
    import os

    from repaint_nerf.app.benchdocs import details, headline, sources
    from repaint_nerf.app.benchdocs.text import replace_between

    known, others = sources.load_all(bench_dir)
    link = Path(os.path.relpath(out.resolve(), readme_dir.resolve())).as_posix()
    note = (f"Every figure with its details: [{link}]({link}). To measure again, run the commands named, then "
            "`repaint-nerf docs`, which writes this table and that page from the benches' JSON in docs/bench/.")
    table = headline.markdown(known) + "\n\n" + note
    return replace_between(readme, BEGIN, END, table), details.markdown(known, others, bench_dir, out.parent)


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.errors import UserError

    readme_path, out = Path(args.readme), Path(args.out)
    if not readme_path.is_file():
        raise UserError("no README here", readme_path, "run from the repository root or pass --readme")
    readme = readme_path.read_text()
    try:
        new_readme, page = render(Path(args.bench_dir), readme, readme_path.parent, out)
    except ValueError as exc:
        raise UserError(str(exc), readme_path, f"put the two marker lines {BEGIN} and {END} where the table goes")
    stale = [p for p, text in ((readme_path, new_readme), (out, page)) if not p.is_file() or p.read_text() != text]
    if args.check:
        for p in stale:
            print(f"out of date: {p} (run `repaint-nerf docs`)")
        return 1 if stale else 0
    readme_path.write_text(new_readme)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(page)
    print(f"wrote {out} and the figure table of {readme_path}" + ("" if stale else " (unchanged)"))
    return 0
