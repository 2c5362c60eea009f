"""The docs name only what exists: every config group and option, config key and repository file that README.md,
docs/*.md, experiments/README.md and ``torchtrack --help`` name is one of the composed configs' (the default, each
group's option files, the console scripts' ``learn`` and ``record`` configs) or a path in the tree.

What is read as a reference, so that prose is not:
- ``group=option`` and ``group.key=value`` words in inline code spans, shell code blocks and the help text (a value
  may list alternatives, ``a|b``, or options, ``[a,b]``; an upper-case or empty value is a placeholder; ``label=...``
  whose value is itself an override, as ``evaluate.py --method=base=filter.gate=0.99`` takes, is read for its value);
- a code span that is one dotted word whose first part is a group or a top-level key (```select.roi_fraction```),
  and the same dotted words in the help text;
- paths that start with ``torchtrack/``, ``conf/``, ``experiments/``, ``docs/`` or ``tests/``.
Python code blocks, ``hydra.*`` keys, environment variables and words with placeholders (``<name>``, ``*``) are not
references.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from torchtrack.cli import compose_config

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
DOCS = [
    "README.md",
    "experiments/README.md",
    *sorted(p.relative_to(REPO).as_posix() for p in (REPO / "docs").glob("*.md")),
]
HELP = "conf/hydra/help/torchtrack.yaml"

# Keys of the console scripts that are not config keys: the CLI's own (`conf_dir`).
CLI_KEYS = {"conf_dir"}
# Words that stand for the form of an override, not for one.
FORMS = {"key=value", "group=option"}
# Paths that are not the repository's: the built wheel's copy of conf/ (setup.py).
NOT_IN_TREE = {"torchtrack/conf"}

OVERRIDE = re.compile(r"^(?P<op>\+{0,2}|~)(?P<key>[a-z_][a-z0-9_]*(?:\.[A-Za-z0-9_]+)*)=(?P<value>[^=].*|)$")
OPTION = re.compile(r"^[a-z_][a-z0-9_]*(?:[|,][a-z_][a-z0-9_]*)*$")  # an option (a|b, a,b) as a value
USER_FILE = re.compile(r"(?<![\w.-])(?!conf/)[\w.-]*/(?P<group>[a-z_]+)/(?P<option>\w+)\.yaml")
DOTTED = re.compile(r"^~?(?P<key>[a-z_][a-z0-9_]*(?:\.[A-Za-z0-9_]+)+)$")
PATH = re.compile(r"(?<![\w/.$-])((?:torchtrack|conf|experiments|docs|tests)/[A-Za-z0-9_./-]*)")
SPAN = re.compile(r"`([^`\n]+)`")
FENCE = re.compile(r"^\s*```(\w*)")


def _paths(node, prefix="") -> set[str]:
    """Every dotted key of ``node`` (inner nodes included)."""
    out = set()
    if isinstance(node, DictConfig):
        for k in node.keys():
            key = f"{prefix}{k}"
            out.add(key)
            child = node._get_node(k)
            if isinstance(child, DictConfig) and not child._is_missing() and not child._is_none():
                out |= _paths(child, key + ".")
    return out


def _groups() -> dict[str, set[str]]:
    """Config group -> its options (the YAML files under conf/<group>/; Hydra's own folder left out)."""
    return {
        d.name: {p.stem for p in d.glob("*.yaml")}
        for d in CONF.iterdir()
        if d.is_dir() and d.name != "hydra" and any(d.glob("*.yaml"))
    }


@lru_cache(maxsize=1)
def known() -> tuple[dict[str, set[str]], frozenset[str], frozenset[str]]:
    """(groups and their options, every dotted key of every composed config, the top-level keys)."""
    groups = _groups()
    defaults = {}  # group -> the option the default config and the learn config compose
    for name in ("config", "learn"):
        for entry in OmegaConf.load(CONF / f"{name}.yaml").defaults:
            if isinstance(entry, DictConfig):
                defaults.update({k: v for k, v in entry.items() if not k.startswith("override")})
    configs = [compose_config("config", []), compose_config("learn", []), compose_config("record", ["out=x"])]
    for group, options in groups.items():
        for o in sorted(options - {defaults.get(group)}):
            if group in ("dataset", "train"):  # the learn config's groups
                configs.append(compose_config("learn", [f"{group}={o}"]))
            else:
                configs.append(compose_config("config", [f"+{group}={o}" if group == "experiment" else f"{group}={o}"]))
    keys = set().union(*(_paths(c) for c in configs))
    top = {k for k in keys if "." not in k} | CLI_KEYS
    return groups, frozenset(keys), frozenset(top)


def _option_values(value: str) -> list[str] | None:
    """The options a group override names (``a``, ``a|b``, ``[a,b]``); None for a placeholder."""
    value = value.strip("'\",;:)")
    if not value or value == "..." or not re.fullmatch(r"[\[\]\w|,.-]+", value) or re.search(r"[A-Z]", value):
        return None
    return [v for v in re.split(r"[\[\],|]", value) if v]


def _dotted_key(word: str) -> str | None:
    """The dotted key a bare word names (``select.roi_fraction``, ``~dataset.modes.object``), else None."""
    m = DOTTED.match(word.rstrip(".:"))
    if m is None:
        return None
    last = m["key"].rsplit(".", 1)[1]
    if last in {"py", "yaml", "md", "json", "txt", "csv", "png", "ply", "pt", "sh", "cpp", "npy", "log"}:
        return None
    return m["key"]


def _check_word(word: str, groups, keys, top, firsts: set[str], user: set[tuple[str, str]]) -> str | None:
    """Why ``word`` (one override or one dotted key) names nothing that exists; None when it does or is no reference."""
    word = word.strip("'\"(),;")
    while word.startswith("-"):  # --method=label=override: the part after the option's own name
        if "=" not in word:
            return None
        word = word.split("=", 1)[1].strip("'\"")
    m = OVERRIDE.match(word)
    if m is None:
        d = _dotted_key(word)
        if d is None or d.split(".")[0] not in firsts or d in keys:
            return None  # no dotted key (a module, a file, out.lost), or one that exists
        return f"no config key '{d}'"
    key, value = m["key"], m["value"]
    if key.split(".")[0] == "hydra" or value == "" or word in FORMS:
        return None
    if "=" in value and "." not in key:  # label=override (a script's named configuration)
        return _check_word(value, groups, keys, top, firsts, user)
    if "." in key:
        if any(part.isupper() for part in key.split(".")):
            return None  # data.KEY: a placeholder
        return None if key in keys else f"no config key '{key}'"
    if key in groups:
        options = _option_values(value)
        bad = [o for o in options or [] if o not in groups[key] and (key, o) not in user]
        return f"no option {', '.join(repr(o) for o in bad)} in group '{key}' (conf/{key}/)" if bad else None
    if key in top or m["op"] == "+" or not OPTION.match(value.strip("'\"")):
        return None  # a top-level key; a key added with +; a script's label for a path or a number
    return f"no config group or key '{key}'"


def stale_references(text: str, source: str, *, help_text: bool = False) -> list[str]:
    """``source:line: token: why`` for each config group, option, key or repository path that ``text`` names and that
    does not exist. ``help_text``: every word is a reference candidate (the help template has no code spans)."""
    groups, keys, top = known()
    contexts: list[tuple[int, str, bool]] = []  # (line, text, a single inline span)
    fence = None
    for n, line in enumerate(text.splitlines(), 1):
        f = FENCE.match(line)
        if f:
            fence = None if fence is not None else f[1]
            continue
        if help_text:
            contexts.append((n, line, False))
        elif fence is not None:
            if fence not in ("python", "py"):
                contexts.append((n, line, False))
        else:
            contexts += [(n, s, True) for s in SPAN.findall(line) if "(" not in s]  # a Python call is no override
    # A dotted word is a key when its first part is a group or the first part of an override (`tracker.x=`, `tracker=icp`).
    overrides = [m for _, t, _ in contexts for w in t.split() if (m := OVERRIDE.match(w.strip("'\"")))]
    firsts = set(groups) | {m["key"].split(".")[0] for m in overrides if "." in m["key"] or OPTION.match(m["value"])}
    user = {(m["group"], m["option"]) for m in USER_FILE.finditer(text)}  # DIR/weighting/mine.yaml: weighting=mine
    out = []
    for n, t, span in contexts:
        words = [w.strip("'\"(),;") for w in t.split()]
        for w in words:
            if "=" in w or ((help_text or (span and len(words) == 1)) and _dotted_key(w) is not None):
                why = _check_word(w, groups, keys, top, firsts, user)
                if why:
                    out.append(f"{source}:{n}: {w}: {why}")
    for n, line in enumerate(text.splitlines(), 1):
        for p in PATH.findall(line):
            p = p.rstrip(".,:;")
            if p in NOT_IN_TREE or re.search(r"[a-z][A-Z]+(?:\.|/|$)", p):  # ekfN.yaml: a placeholder
                continue
            if not (REPO / p).exists():
                out.append(f"{source}:{n}: {p}: no such file or folder in the repository")
    return out


def test_the_docs_name_only_groups_options_keys_and_files_that_exist():
    stale = []
    for doc in DOCS:
        stale += stale_references((REPO / doc).read_text(), doc)
    stale += stale_references((REPO / HELP).read_text(), HELP, help_text=True)
    assert not stale, "the docs name what does not exist (update these lines):\n" + "\n".join(stale)


def test_the_scanner_reports_each_stale_token_with_its_line():
    text = "\n".join(
        [
            "Run `torchtrack weighting=fixed select.lam=1.0` or `+experiment=[ekf1,ekf2]`.",  # 1: fine
            "The switch `pipeline.predict_init` and `data.root=DIR`, `tracker=icp|horn`.",  # 2: fine
            "Renamed: `pipeline.predict_initial` and `filter.gat=0.9`.",  # 3: two stale keys
            "```bash",  # 4
            "torchtrack weighting=learnt estimatr=icp 'data.root=[A,B]' --method=base=filter.gate=0.9",  # 5: two
            "```",  # 6
            "```python",  # 7
            "RGBDTracker(K, depth_scale=1000, overrides=['weighting=nope'])",  # 8: code, not a reference
            "```",  # 9
            "Files: `conf/weighting/learned.yaml`, conf/weighting_tracker/learned_fusion_ekf.yaml, docs/nope.md.",  # 10
            "Prose with metrics.json, out.lost and torchtrack.stream.RGBDTracker names no key.",  # 11: fine
            "`dense.every=10` and `dense.nope`; label `lm=landmarks.enabld=true`; empty `off=`.",  # 12: two
        ]
    )
    found = stale_references(text, "t.md")
    expected = [
        "t.md:3: pipeline.predict_initial: no config key 'pipeline.predict_initial'",
        "t.md:3: filter.gat=0.9: no config key 'filter.gat'",
        "t.md:5: weighting=learnt: no option 'learnt' in group 'weighting' (conf/weighting/)",
        "t.md:5: estimatr=icp: no config group or key 'estimatr'",
        "t.md:12: dense.nope: no config key 'dense.nope'",
        "t.md:12: lm=landmarks.enabld=true: no config key 'landmarks.enabld'",
        "t.md:10: conf/weighting_tracker/learned_fusion_ekf.yaml: no such file or folder in the repository",
        "t.md:10: docs/nope.md: no such file or folder in the repository",
    ]
    assert found == expected


def test_a_renamed_key_option_or_file_in_a_real_doc_is_reported():
    readme = (REPO / "README.md").read_text()
    assert stale_references(readme, "README.md") == []
    for good, bad in [
        ("`pipeline.predict_init`", "`pipeline.predict_initial`"),
        ("`filter.gate`", "`filter.gating`"),
        ("region=object", "region=objet"),
        ("weighting=learned", "weighting=learnt"),
        ("docs/extending.md", "docs/extend.md"),
        ("`select.lam=1.0`", "`select.lamda=1.0`"),
    ]:
        assert good in readme, good
        stale = stale_references(readme.replace(good, bad, 1), "README.md")
        assert len(stale) == 1 and bad.strip("`").split("=")[0] in stale[0], (bad, stale)
        line = readme[: readme.index(good)].count("\n") + 1
        assert stale[0].startswith(f"README.md:{line}: "), stale
