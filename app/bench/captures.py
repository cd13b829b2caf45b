"""`repaint-nerf bench captures`: list the public real captures the benchmarks use (core/bench/captures.py) and
prepare one from a fetched snapshot into a local folder outside the repository (core/bench/capture_prepare.py)."""
from __future__ import annotations

import argparse
from pathlib import Path

from repaint_nerf.core.bench.captures import CAPTURES, default_root, find_capture

HELP = "list the public real captures, or prepare one from a fetched snapshot into a local capture folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--list", action="store_true", help="list the registered captures and where they come from")
    what.add_argument("--prepare", metavar="NAME", help="copy capture NAME out of --from into --dest/NAME")
    what.add_argument("--table", metavar="NAME=OURS.json[,NERFACTO.json]", action="append",
                      help="gather a capture's bench recon (and bench nerfacto) JSON into one side-by-side table "
                           "(repeat per capture; with --json, e.g. docs/bench/captures.json for repaint-nerf docs)")
    p.add_argument("--json", default=None, help="with --table: where to write the table")
    p.add_argument("--machine", default="", help="with --table: how the runs were taken (cores, threads), in words")
    p.add_argument("--update", action="store_true",
                   help="with --table and --json: replace only the captures given, keeping the other rows of the "
                        "existing table (each row keeps its own date and command); a capture given with OURS.json "
                        "alone keeps its nerfacto row, and a colour-alone run keeps the --as-train one (and the "
                        "other way round)")
    p.add_argument("--from", dest="source", default=None,
                   help="the fetched snapshot's git directory (e.g. /work/.mirror/OWNER+NAME/repo) or a plain folder")
    p.add_argument("--dest", default=None, help=f"folder that receives NAME/ (default {default_root()})")
    p.add_argument("--commit", default=None, help="commit to copy (default: the registered one; HEAD: the newest)")
    p.add_argument("--shrink", default="", help="also write images_N/ copies shrunk by these factors, e.g. 4,8")
    p.add_argument("--force", action="store_true", help="replace a capture folder prepared before")


def _factors(text: str) -> tuple[int, ...]:
    from repaint_nerf.core.errors import UserError

    try:
        return tuple(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise UserError(f"--shrink takes whole factors separated by commas, got {text!r}", hint="e.g. --shrink 4,8") \
            from None


def _table(args: argparse.Namespace) -> int:
    import json

    from repaint_nerf.core.bench.captures import METHODS, side_by_side
    from repaint_nerf.core.errors import UserError

    rows, firsts = {}, []
    for item in args.table:
        name, _, files = item.partition("=")
        paths = [Path(f) for f in files.split(",") if f]
        if not name or not 1 <= len(paths) <= 2:
            raise UserError(f"--table takes NAME=OURS.json[,NERFACTO.json], got {item!r}",
                            hint="e.g. --table fox=recon-fox.json,nerfacto-fox.json")
        try:
            loaded = [json.loads(p.read_text()) for p in paths]
        except (OSError, ValueError) as exc:
            raise UserError(f"cannot read {item!r}: {exc}", hint="give the JSON files bench recon and bench "
                                                                 "nerfacto wrote") from None
        rows[name] = side_by_side(loaded[0], loaded[1] if len(loaded) > 1 else None)
        firsts.append(loaded[0])
    devices = sorted({str(d.get("device")) for d in firsts if d.get("device")})
    old = {}
    if args.update:
        if not args.json or not Path(args.json).is_file():
            raise UserError("--update needs --json naming an existing table", hint="drop --update to write a new one")
        try:
            old = json.loads(Path(args.json).read_text())
        except ValueError as exc:
            raise UserError(f"{args.json} is not a table bench captures wrote ({exc})") from None
        devices = sorted(set(devices) | {d for d in str(old.get("device", "")).split(", ") if d and d != "?"})
        for name, row in rows.items():  # one method re-measured (a speed-up): the others' runs stand
            for method in METHODS:
                if row.get(method) is None:
                    row[method] = (old.get("captures", {}).get(name) or {}).get(method)
    table = {"machine": args.machine or old.get("machine", ""), "device": ", ".join(devices) or "?",
             "report_at": ["60", "120", "300"], "captures": {**old.get("captures", {}), **rows}}
    text = json.dumps(table, indent=1)
    if args.json:
        Path(args.json).write_text(text + "\n")
        print(f"wrote {args.json}")
    else:
        print(text)
    return 0


def run(args: argparse.Namespace) -> int:
    from repaint_nerf.core.bench.capture_prepare import prepare
    from repaint_nerf.core.errors import UserError

    if args.table:
        return _table(args)
    if args.list:
        root = Path(args.dest).expanduser() if args.dest else default_root()
        for c in CAPTURES:
            where = root / c.name
            print(f"{c.name}: {c.kind}\n  github:{c.repo} @ {c.commit[:12]}, {c.path or '(root)'}\n  {c.layout}; "
                  f"{c.images}\n  licence: {c.licence}\n  " + (f"prepared: {where}" if where.is_dir() else
                                                               "not prepared") + (f"\n  note: {c.note}" if c.note else ""))
        return 0
    cap = find_capture(args.prepare)
    if not args.source:
        raise UserError("--prepare needs --from: the snapshot's git directory or a folder holding the capture",
                        hint=f"fetch github:{cap.repo}, then --from /work/.mirror/{cap.repo.replace('/', '+')}/repo")
    res = prepare(cap, Path(args.source), Path(args.dest) if args.dest else default_root(), args.commit,
                  _factors(args.shrink), args.force)
    print(f"prepared {cap.name} in {res.folder}: {res.copied} files copied")
    if res.missing:
        print(f"warning: {len(res.missing)} file(s) listed by the snapshot are absent there and were not copied, "
              f"e.g. {', '.join(res.missing[:3])}")
    for f, n in res.shrunk.items():
        print(f"images_{f}/: {n} images written" if n else f"images_{f}/: kept as shipped (or no images/ folder)")
    print(f"bench it: repaint-nerf bench recon --scene {res.folder} --seconds 300 --json recon-{cap.name}.json")
    return 0
