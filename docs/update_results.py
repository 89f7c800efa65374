"""Fill the documentation's results pages from the files the benchmarks and the demo wrote.

    python docs/update_results.py [demo-output.txt]

Replaces the text between the markers ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->``
in the pages under ``docs/`` (each marker pair is on exactly one page: ``docs/results/*.md``, the
demo's in ``docs/quickstart.md``) with the table read from its source, so that the pages quote
real runs verbatim.  ``docs/results/raw.md`` includes every file of ``benchmarks/results/`` as
it stands when the site is built.
"""
from __future__ import annotations

import pathlib
import re
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def tables(text: str) -> list[str]:
    """The markdown tables of a text, with the line that follows each (a verdict) if any."""
    out, cur = [], []
    for line in text.splitlines():
        if line.startswith("|"):
            cur.append(line)
        elif cur:
            out.append("\n".join(cur))
            cur = []
    if cur:
        out.append("\n".join(cur))
    return out


def pages() -> list[pathlib.Path]:
    """The documentation's Markdown pages (not the build's output or the generated gallery)."""
    skip = {"_build", "auto_tutorials", "_generated", "figures"}
    return sorted(p for p in (ROOT / "docs").rglob("*.md")
                  if not skip.intersection(p.relative_to(ROOT / "docs").parts))


def main() -> None:
    texts = {p: p.read_text() for p in pages()}
    parts = {}
    reb = (ROOT / "benchmarks/results/rebound.md").read_text()
    parts["rebound"] = "\n\n".join(
        f"**{title}**\n\n" + body.strip()
        for title, body in re.findall(r"^## (.*?)$\n(.*?)(?=^## |\Z)", reb, re.S | re.M))
    ada = ROOT / "benchmarks/results/adaptive.md"
    if ada.exists():
        parts["adaptive"] = "\n\n".join(
            f"**{title}**\n\n" + body.strip()
            for title, body in re.findall(r"^## (.*?)$\n(.*?)(?=^## |\Z)", ada.read_text(), re.S | re.M))
    tp = ROOT / "benchmarks/results/testparticles.md"
    if tp.exists():        # everything after the title
        parts["testparticles"] = tp.read_text().split("\n\n", 1)[1].strip()
    dfl = ROOT / "benchmarks/results/defaults.md"
    if dfl.exists():
        text = dfl.read_text()
        parts["defaults"] = text[text.index("**"):].strip()
    kep = (ROOT / "benchmarks/results/kepler.md").read_text()
    parts["kepler"] = tables(kep)[0]
    md = (ROOT / "benchmarks/results/md.md").read_text()
    parts["md"] = md.splitlines()[0] + "\n\n" + tables(md)[0]
    cost = ROOT / "benchmarks/results/md_cost.md"
    if cost.exists():
        parts["md_cost"] = cost.read_text().strip()
    kc = ROOT / "benchmarks/results/kepler_composed.md"
    if kc.exists():        # the issue-48 speed bars' table, with the run's header line
        text = kc.read_text()
        m = re.search(r"^## The issue's speed bars.*?$\n(.*?)(?=^## |\Z)", text, re.S | re.M)
        if m:
            parts["kepler_composed"] = text.splitlines()[2] + "\n\n" + m.group(1).strip()
    if len(sys.argv) > 1:
        demo = pathlib.Path(sys.argv[1]).read_text()
        t = tables(demo)
        heads = re.findall(r"^== (.*)$", demo, re.M)
        parts["demo"] = "\n\n".join(f"*{h}*\n\n{tb}" for h, tb in zip(heads, t))
    for name, body in parts.items():
        pat = re.compile(rf"(<!-- results:{name} -->\n).*?(<!-- /results:{name} -->)", re.S)
        where = [p for p, text in texts.items() if pat.search(text)]
        if len(where) != 1:
            raise SystemExit(f"the markers for {name!r} must be on exactly one page under docs/ "
                             f"(found on {[str(p.relative_to(ROOT)) for p in where]})")
        texts[where[0]] = pat.sub(lambda m: m.group(1) + body + "\n" + m.group(2), texts[where[0]])
    changed = [p for p, text in texts.items() if text != p.read_text()]
    for p in changed:
        p.write_text(texts[p])
    print("filled:", ", ".join(parts), "; pages changed:",
          ", ".join(str(p.relative_to(ROOT)) for p in changed) or "none")


if __name__ == "__main__":
    main()
