"""The config reference, docs/config.md, generated from the spec dataclasses: every config group registered in
codesign/config/store.py (and the material group of conf/material/), each key with its default and the text of its
spec's docstring that explains it (units as the docstrings give them).

    python -m codesign.config.reference            # rewrite docs/config.md
    python -m codesign.config.reference --check    # exit 1 when docs/config.md is not current

tests/test_discoverability.py checks that the file is current, so that it cannot go stale.
"""
from __future__ import annotations

import inspect
import json
import re
import sys
from dataclasses import MISSING, fields, is_dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
OUTPUT = ROOT / "docs" / "config.md"
_BLOCK = object()  # the default of a key that holds a block of keys (listed after it)

# the root keys that some experiments add (conf/experiment/*.yaml: ``- /root_keys/NAME: OPTION``); no spec has them
_ROOT_KEY_DOCS = {
    "precision": "float32 | float64: the floating-point precision of the optics computation",
    "checkpoint": "a training checkpoint path (required)",
    "input": "a capture file or a folder of captures (required)",
}


def _doc(cls) -> str:
    return inspect.cleandoc(cls.__doc__ or "") if cls.__doc__ and not cls.__doc__.startswith(cls.__name__ + "(") \
        else ""


def _label_re(names: list[str]) -> re.Pattern:
    """A label naming one or more of ``names``: ``a: ``, ``a, b: ``, ``a / b: ``, ``a (note), b: ``."""
    name = r"(?:%s)(?:\s*\([^()]*\))?" % "|".join(sorted(map(re.escape, names), key=len, reverse=True))
    return re.compile(r"(?<![\w.])(%s(?:(?:\s*,\s*|\s*/\s*|\s+and\s+)%s)*):(?=\s)" % (name, name))


def _clean(text: str) -> str:
    text = " ".join(text.split()).strip()
    text = re.sub(r"(?:\s*Attributes:)$", "", text).strip()
    return text.rstrip(";,").strip()


def _explanations(doc: str, names: list[str]) -> tuple[str, dict[str, str]]:
    """The docstring's text before its first key label, and each key's labelled text (up to the next label)."""
    if not doc or not names:
        return _clean(doc), {}
    labels = list(_label_re(names).finditer(doc))
    intro = _clean(doc[:labels[0].start()] if labels else doc)
    out: dict[str, str] = {}
    for i, m in enumerate(labels):
        end = labels[i + 1].start() if i + 1 < len(labels) else len(doc)
        text = _clean(doc[m.start():end])
        for key in re.findall(r"[A-Za-z_]\w*", re.sub(r"\([^()]*\)", "", m.group(1))):
            if key in names and key not in out:
                out[key] = text
    return intro, out


def _mention(doc: str, key: str, names: list[str]) -> str:
    """The text of ``doc`` that names ``key`` without a label: its clause (e.g. ``level_noise_m [m]``), or, where
    the key is only referred to (``key``, or a bare name), the labelled passage around it; '' when not named."""
    m = re.search(r"``%s``" % re.escape(key), doc) or re.search(r"(?<![\w.])%s(?![\w])" % re.escape(key), doc)
    if not m:
        return ""
    depth, i = 0, m.start()
    while i < len(doc):
        c = doc[i]
        depth += c in "(["
        depth -= c in ")]"
        if depth < 0 or (depth == 0 and (c in ";," or (c == "." and doc[i + 1:i + 2] in (" ", "\n", "")))):
            break
        i += 1
    clause = _clean(doc[m.start():i])
    if clause.strip("`") != key and not clause.startswith("``"):
        return clause
    labels = [lab.start() for lab in _label_re(names).finditer(doc)]
    start = max((s for s in labels if s <= m.start()), default=0)
    end = min((s for s in labels if s > m.start()), default=len(doc))
    return _clean(doc[start:end])


def _value(value) -> str:
    text = json.dumps(value, default=str)
    return "`" + text + "`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|") if text else "—"


def _field_default(f):
    return f.default_factory() if f.default_factory is not MISSING else f.default


def _rows(cls, node: dict, extra: tuple[type, ...], prefix: str = "") -> list[tuple[str, object, str]]:
    """(key, default, meaning) of every key of ``node``, explained by ``cls``'s docstring (and its bases')."""
    specs = [c for c in cls.__mro__ if is_dataclass(c)] if is_dataclass(cls) else []
    names = [f.name for f in fields(cls)] if is_dataclass(cls) else []
    names = sorted(set(names) | set(node))
    found: dict[str, str] = {}
    for c in specs:
        for key, text in _explanations(_doc(c), names)[1].items():
            found.setdefault(key, text)
    kinds = {f.name: _field_default(f) for f in fields(cls)} if is_dataclass(cls) else {}
    rows = []
    for key, value in node.items():
        sub = kinds.get(key)
        nested = type(sub) if is_dataclass(sub) else next(
            (c for c in extra if isinstance(value, dict) and set(value) == {f.name for f in fields(c)}), None)
        meaning = found.get(key) or next((m for c in specs if (m := _mention(_doc(c), key, names))), "")
        if nested is not None and isinstance(value, dict):
            intro = _explanations(_doc(nested), [f.name for f in fields(nested)])[0]
            rows.append((prefix + key, _BLOCK, meaning or intro or f"the {nested.__name__} block below"))
            rows.extend(_rows(nested, value, extra, prefix + key + "."))
            continue
        rows.append((prefix + key, value, meaning))
    return rows


def _table(rows, group_key: str) -> list[str]:
    out = ["| key | default | meaning |", "|---|---|---|"]
    for key, value, meaning in rows:
        shown = "(block)" if value is _BLOCK else _value(value)
        out.append(f"| `{group_key}{key}` | {shown} | {_cell(meaning)} |")
    return out


def _registered() -> dict[str, dict[str, tuple[dict, tuple[type, ...], str | None]]]:
    """group -> option -> (node, specs, package), in registration order."""
    import codesign  # noqa: F401  (imports every spec module: their registrations)
    from hydra.core.config_store import ConfigStore
    from omegaconf import OmegaConf

    from codesign.config.store import SPECS

    store = ConfigStore.instance()
    out: dict[str, dict[str, tuple]] = {}

    def walk(tree: dict, path: str) -> None:
        for key, item in tree.items():
            if isinstance(item, dict):
                walk(item, f"{path}{key}/")
            elif path and key.endswith(".yaml"):
                group, option = path.rstrip("/"), key[:-len(".yaml")]
                if group == "hydra" or group.startswith("hydra/"):  # Hydra's own (launchers, sweepers: their
                    continue  # plugins register on import, so what is there depends on what ran before)
                node = OmegaConf.to_container(item.node, resolve=False)
                out.setdefault(group, {})[option] = (node, SPECS.get((group, option), ()), item.package)

    walk(store.repo, "")
    return out


def _yaml_group_section(group: str, cls: type) -> list[str]:
    """A group whose options are conf/GROUP/*.yaml (e.g. material): its keys are the fields of ``cls``, shown with
    the dataclass's defaults."""
    from omegaconf import OmegaConf

    options = sorted(p.stem for p in (ROOT / "conf" / group).glob("*.yaml"))
    chosen = [d[group] for d in OmegaConf.to_container(OmegaConf.load(ROOT / "conf" / "config.yaml"))["defaults"]
              if isinstance(d, dict) and group in d]
    node = {f.name: json.loads(json.dumps(_field_default(f))) for f in fields(cls) if f.name != "prefix"}
    lines = [f"## {group}", "", f"Options: {', '.join(f'`{group}={o}`' for o in options)} (conf/{group}/"
             + (f"; the default is `{group}={chosen[0]}`" if chosen else "") + "). The defaults shown are the "
             f"spec's. Spec: `{cls.__module__}.{cls.__name__}`.", ""]
    intro = _explanations(_doc(cls), list(node))[0]
    if intro:
        lines += [intro, ""]
    return lines + _table(_rows(cls, node, ()), f"{group}.") + [""]


def generate() -> str:
    """The text of docs/config.md: every config group's keys with their defaults and their specs' explanations."""
    groups = _registered()
    lines = [
        "# Configuration reference",
        "",
        "<!-- generated by `python -m codesign.config.reference` from the spec dataclasses; do not edit by hand "
        "(tests/test_discoverability.py checks that it is current) -->",
        "",
        "Every config group, each key with its default and the text of its spec's docstring that explains it. "
        "Units are as the docstrings give them: `[m]`, `[rad]`, `[s]`; a key's suffix says its unit too "
        "(`_m` metres, `_s` seconds, `_rad` radians, `_deg` degrees, `_e` electrons, `_mb` MiB). Set a key on the "
        "command line as `group.key=value` (e.g. `optics.focal_n=320`), choose a group's option as `group=option` "
        "(e.g. `mask=pixel`), and print the composed configuration of a run with "
        "`python -m codesign +experiment=NAME --cfg job`. The experiments themselves: `python -m codesign --help`.",
        "",
        "Groups: " + ", ".join(f"[{g}](#{g.replace('/', '')})" for g in _group_order(groups)) + ".",
        "",
    ]
    from codesign.config.store import YAML_GROUPS

    for group in _group_order(groups):
        if group in YAML_GROUPS and group not in groups:
            lines += _yaml_group_section(group, YAML_GROUPS[group])
            continue
        options = groups[group]
        if group == "root_keys":
            continue
        lines += _group_section(group, options)
    roots = {g.split("/", 1)[1]: o for g, o in groups.items() if g.startswith("root_keys/")}
    if roots:
        lines += ["## root_keys", "", "Root keys that some experiments add (their conf/experiment/NAME.yaml lists "
                  "`- /root_keys/KEY: OPTION`).", "", "| key | default | meaning | experiments |", "|---|---|---|---|"]
        for key, options in roots.items():
            users = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml")
                           if f"/root_keys/{key}:" in p.read_text())
            for option, (node, _, _) in options.items():
                for k, v in node.items():
                    lines.append(f"| `{k}` | {_value(v)} | {_cell(_ROOT_KEY_DOCS.get(k, ''))} | "
                                 f"{', '.join(users) or '—'} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def _group_order(groups: dict) -> list[str]:
    """The registered groups in registration order, each YAML-only group (material) before mask (else last)."""
    from codesign.config.store import YAML_GROUPS

    order = [g for g in groups if not g.startswith("root_keys/")]
    for group in YAML_GROUPS:
        if group not in order:
            order.insert(order.index("mask") if "mask" in order else len(order), group)
    return order


def _group_section(group: str, options: dict) -> list[str]:
    names = list(options)
    first_node, first_specs, package = options[names[0]]
    at_root = package == "_global_"
    key_prefix = "" if at_root else f"{group}."
    head = f"## {group}"
    lines = [head, ""]
    if len(names) > 1:
        lines += [f"Options: {', '.join(f'`{group}={n}`' for n in names)}.", ""]
    elif at_root:
        lines += [f"Root keys (`{group}={names[0]}` puts them at the top level of the config).", ""]
    shown: dict[type, tuple[str, dict]] = {}
    for name in names:
        node, specs, _ = options[name]
        cls = specs[0] if specs else None
        title = f"### {group}={name}" if len(names) > 1 else None
        spec_note = f"Spec: `{cls.__module__}.{cls.__name__}`." if cls else ""
        if cls in shown and cls is not None:
            base_name, base_node = shown[cls]
            rows = [r for r in _rows(cls, node, specs[1:]) if _lookup(base_node, r[0]) != r[1]]
            lines += [title, "", f"As `{group}={base_name}`, except:", ""] if title else []
            lines += _table(rows, key_prefix) + [""] if rows else ["(no difference)", ""]
            continue
        if cls is not None:
            shown[cls] = (name, node)
        lines += [title, ""] if title else []
        intro = ""
        if cls is not None:
            names_ = sorted({f.name for f in fields(cls)} | set(node))
            intro = _explanations(_doc(cls), names_)[0]
        if intro and intro[-1] not in ".:":
            intro += "."
        lines += [" ".join(t for t in (intro, spec_note) if t), ""] if intro or spec_note else []
        lines += _table(_rows(cls, node, specs[1:]), key_prefix) + [""]
    return lines


def _lookup(node: dict, dotted: str):
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return MISSING
        node = node[part]
    return node


def main(argv: list[str] | None = None) -> int:
    """Write docs/config.md (``--check``: only say whether it is current, exit 1 when not); returns the exit status."""
    argv = sys.argv[1:] if argv is None else argv
    text = generate()
    if "--check" in argv:
        current = OUTPUT.read_text() if OUTPUT.exists() else ""
        if current != text:
            print(f"{OUTPUT} is not current: run python -m codesign.config.reference", file=sys.stderr)
            return 1
        print(f"{OUTPUT} is current")
        return 0
    OUTPUT.write_text(text)
    print(f"wrote {OUTPUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
