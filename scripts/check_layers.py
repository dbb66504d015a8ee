#!/usr/bin/env python3
"""The module import graph of one Rust crate, its import cycles, and a check against a layer order.

Usage:
    python3 scripts/check_layers.py SRC [--layers FILE] [--graph | --dot] [--root FILE]

    SRC        the crate's source folder (crates/render/src); the root is SRC/lib.rs, else
               SRC/main.rs (--root names another)
    --layers   a layer order file: one line per layer, lowest first, the modules of a layer on one
               line separated by spaces (`apart:` first: they may not import each other); `#`
               starts a comment
    --graph    print the graph as an edge list (`a -> b  file:line`, the first place the import is)
    --dot      print the graph in Graphviz DOT

It prints the number of modules and imports, every import cycle (each strongly connected
component of more than one module, with one import of each edge inside it) and, with --layers,
every import of a module in a higher layer. It exits 0 when there is no cycle and (with --layers)
no upward import, 1 when there is either, and 2 when the crate or the layer file cannot be read
or the layer file does not match the crate (a module it names does not exist, a module exists
that no layer covers, a module is named twice), so that a stale layer file can never pass.

What counts as an import (the rules, decided here once):
- Nodes are the crate's file modules: the root (`crate`) and every module declared with `mod x;`
  and found as x.rs or x/mod.rs (or through `#[path]`), named by path (`gpu::kernels`). An inline
  module (`mod tests { ... }`) is part of the file that holds it: its imports are that file's.
- A `mod` declaration is nesting, not an import: declaring a child makes no edge.
- An edge A -> B is any path in A's code (a `use` item, or a path in expressions, types, impls and
  attributes' code, tests included) that names an item defined in B: `crate::b::X`, `super::X`,
  `self::b::X`, `b::X` with b a child, `$crate::b::X`. Comments, doc comments and strings are not
  code: a doc link is not an import. Paths into other crates are not edges, nor is the path of
  a visibility (`pub(in crate::b)`).
- A path is resolved to where its item is defined, through `use` imports and re-exports: `crate::X`
  where lib.rs has `pub use b::X` is an import of b, not of the root, so a facade that only
  re-exports never becomes a cycle's hub. A path that ends at a module (`use super::kernels`) is an
  import of that module. A name this script cannot find defined (a macro, an enum variant) is
  counted as an import of the module the path reaches.
- A child module naming an item its parent defines is an import of the parent like any other
  (child -> parent). Rust lets a child see its parent's private items, but a parent that defines
  items its children use and also uses its children is a cycle: the parent mixes the children's
  foundation with what is built on them. The usual fix is to move the shared items into a sibling
  module both use, and keep the parent to declarations, re-exports and what is built on top.
- In a layer file a name covers the module and its descendants, unless a descendant is named
  itself; the root may be named as `crate`, and if it is not it sits above every layer. An import
  of a module in the same or a lower layer is allowed; an import of a higher layer is an error.
- A layer line that starts with `apart:` keeps its modules apart: none of them (with what each
  covers) imports another of that line, though each imports the layers below (a binary's
  commands, each built on shared helpers and on no other command).

Standard library only; the lexer knows Rust's comments, strings, raw strings, chars and lifetimes.
Its tests: python3 -m unittest scripts/test_check_layers.py
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from dataclasses import dataclass, field

ROOT = ()  # the crate root's module path


class LayerError(Exception):
    """The crate or the layer file cannot be read, or they do not match."""


# ---------------------------------------------------------------------------------------------
# Lexing


@dataclass
class Tok:
    kind: str  # "id", "str", "life" (lifetime or label), "p" (punctuation), "num"
    text: str
    line: int


_ID_START = re.compile(r"[A-Za-z_]")
_ID = re.compile(r"[A-Za-z0-9_]*")


def lex(src: str) -> list[Tok]:
    """Tokens of Rust source, without comments; strings and chars as single tokens."""
    toks: list[Tok] = []
    i, n, line = 0, len(src), 1
    while i < n:
        c = src[i]
        if c == "\n":
            line += 1
            i += 1
        elif c.isspace():
            i += 1
        elif src.startswith("//", i):
            j = src.find("\n", i)
            i = n if j < 0 else j
        elif src.startswith("/*", i):
            depth, i = 1, i + 2
            while i < n and depth:
                if src.startswith("/*", i):
                    depth, i = depth + 1, i + 2
                elif src.startswith("*/", i):
                    depth, i = depth - 1, i + 2
                else:
                    line += src[i] == "\n"
                    i += 1
        elif c in "rb" and re.match(r'(br|rb|r|b)?#*"', src[i:i + 20]) and _raw_start(src, i):
            i, line = _raw_string(src, i, line, toks)
        elif c == '"' or (c == "b" and src.startswith('b"', i)):
            start_line = line
            j = i + (2 if c == "b" else 1)
            while j < n and src[j] != '"':
                if src[j] == "\\":
                    j += 1
                line += src[j] == "\n" if j < n else 0
                j += 1
            toks.append(Tok("str", src[i + (2 if c == "b" else 1):j], start_line))
            i = j + 1
        elif c == "'" or (c == "b" and src.startswith("b'", i)):
            j = i + (2 if c == "b" else 1)
            if j < n and src[j] == "\\":  # an escaped char literal
                k = src.find("'", j + 2)
                i = n if k < 0 else k + 1
                toks.append(Tok("str", "", line))
            elif j + 1 < n and src[j + 1] == "'":  # a plain char literal
                i = j + 2
                toks.append(Tok("str", src[j], line))
            else:  # a lifetime or a label
                m = _ID.match(src, j)
                toks.append(Tok("life", src[j:m.end()], line))
                i = max(m.end(), j + 1)
        elif src.startswith("r#", i) and i + 2 < n and _ID_START.match(src[i + 2]):
            m = _ID.match(src, i + 3)
            toks.append(Tok("id", src[i + 2:m.end()], line))
            i = m.end()
        elif _ID_START.match(c):
            m = _ID.match(src, i + 1)
            toks.append(Tok("id", src[i:m.end()], line))
            i = m.end()
        elif c.isdigit():
            m = re.compile(r"[0-9A-Za-z_.]*").match(src, i + 1)
            toks.append(Tok("num", src[i:m.end()], line))
            i = m.end()
        elif src.startswith("::", i):
            toks.append(Tok("p", "::", line))
            i += 2
        else:
            toks.append(Tok("p", c, line))
            i += 1
    return toks


def _raw_start(src: str, i: int) -> bool:
    m = re.match(r'(br|rb|r|b)?(#*)"', src[i:i + 40])
    return bool(m) and ("r" in (m.group(1) or ""))


def _raw_string(src: str, i: int, line: int, toks: list[Tok]) -> tuple[int, int]:
    m = re.match(r'(br|rb|r)(#*)"', src[i:i + 40])
    hashes = m.group(2)
    start = i + m.end()
    end = src.find('"' + hashes, start)
    end = len(src) if end < 0 else end
    toks.append(Tok("str", src[start:end], line))
    line += src.count("\n", start, end)
    return end + 1 + len(hashes), line


# ---------------------------------------------------------------------------------------------
# Parsing what matters: mod declarations, use trees, paths, item definitions


@dataclass
class Ref:
    """A crate-local path named at `line`: absolute segments from the crate root, or None."""

    segs: tuple
    line: int
    text: str


@dataclass
class Module:
    path: tuple
    file: str
    children: dict = field(default_factory=dict)  # name -> file path
    defined: set = field(default_factory=set)
    imports: dict = field(default_factory=dict)  # name -> absolute segments
    globs: list = field(default_factory=list)  # absolute segments
    refs: list = field(default_factory=list)  # Ref


_ITEM_KW = {"fn", "struct", "enum", "trait", "type", "const", "static", "union", "mod"}


def parse_module(mod: Module, is_mod_rs: bool) -> None:
    with open(mod.file, encoding="utf-8") as f:
        toks = lex(f.read())
    # The folder a `mod x;` of this file is looked for in.
    here = os.path.dirname(mod.file)
    if mod.path != ROOT and not is_mod_rs:
        here = os.path.join(here, mod.path[-1])

    # The file's child modules first: a path may name one above its `mod` line.
    depth = 0
    for k, t in enumerate(toks):
        if t.kind == "p" and t.text in ("{", "}"):
            depth += 1 if t.text == "{" else -1
        elif depth == 0 and t.text == "mod" and k + 2 < len(toks) and toks[k + 1].kind == "id" \
                and toks[k + 2].text == ";":
            mod.children[toks[k + 1].text] = None

    inline: list[tuple[str, int]] = []  # inline modules open at this point: (name, brace depth)
    depth = 0
    path_attr = None
    i, n = 0, len(toks)
    while i < n:
        t = toks[i]
        if t.kind == "p" and t.text == "{":
            depth += 1
        elif t.kind == "p" and t.text == "}":
            depth -= 1
            if inline and inline[-1][1] == depth:
                inline.pop()
        elif t.kind == "p" and t.text == "#" and i + 5 < n and toks[i + 1].text == "[" \
                and toks[i + 2].text == "path" and toks[i + 3].text == "=" \
                and toks[i + 4].kind == "str":
            path_attr = toks[i + 4].text
            i += 5
            continue
        elif t.kind == "id" and t.text == "mod" and i + 2 < n and toks[i + 1].kind == "id":
            name = toks[i + 1].text
            nxt = toks[i + 2].text
            if not inline and depth == 0:
                mod.defined.add(name)
            if nxt == ";" and not inline and depth == 0:
                mod.children[name] = _child_file(here, os.path.dirname(mod.file), name, path_attr)
            elif nxt == "{":
                inline.append((name, depth))
                depth += 1
                i += 3
                path_attr = None
                continue
            path_attr = None
        elif t.kind == "id" and t.text in _ITEM_KW and i + 1 < n and toks[i + 1].kind == "id" \
                and not inline and depth == 0:
            mod.defined.add(toks[i + 1].text)
        elif t.kind == "id" and t.text == "macro_rules" and i + 2 < n and toks[i + 1].text == "!":
            if not inline and depth == 0:
                mod.defined.add(toks[i + 2].text)
        elif t.kind == "id" and t.text == "use" and not _prev_is(toks, i, "::"):
            j, leaves = _use_tree(toks, i + 1, [])
            for segs, alias, glob in leaves:
                abs_ = _absolute(mod, segs, len(inline))
                if abs_ is None:
                    continue
                mod.refs.append(Ref(abs_, t.line, "use " + "::".join(segs) + ("::*" if glob else "")))
                if glob:
                    if not inline:
                        mod.globs.append(abs_)
                else:
                    name = alias or (segs[-1] if segs[-1] != "self" else segs[-2] if len(segs) > 1 else None)
                    if name and name != "_" and not inline:
                        mod.imports[name] = abs_
            i = j
            continue
        elif t.kind == "id" and i + 1 < n and toks[i + 1].text == "::" and not _prev_is(toks, i, "::") \
                and not (_prev_is(toks, i, "in") and i > 1 and toks[i - 2].text == "(") \
                and (t.text in ("crate", "super", "self") or t.text in mod.children
                     or (t.text == "crate" and _prev_is(toks, i, "$"))):
            segs = [t.text]
            j = i + 1
            while j + 1 < n and toks[j].text == "::" and toks[j + 1].kind == "id":
                segs.append(toks[j + 1].text)
                j += 2
            abs_ = _absolute(mod, segs, len(inline))
            if abs_ is not None:
                mod.refs.append(Ref(abs_, t.line, "::".join(segs)))
            i = j
            continue
        path_attr = None if t.text not in ("#", "[", "]", "cfg", "(", ")") else path_attr
        i += 1


def _prev_is(toks: list[Tok], i: int, text: str) -> bool:
    return i > 0 and toks[i - 1].text == text


def _child_file(here: str, file_dir: str, name: str, path_attr: str | None) -> str:
    if path_attr:  # relative to the folder of the file that declares the module
        return os.path.normpath(os.path.join(file_dir, path_attr))
    for cand in (os.path.join(here, name + ".rs"), os.path.join(here, name, "mod.rs")):
        if os.path.exists(cand):
            return cand
    return os.path.join(here, name + ".rs")  # reported missing when read


def _use_tree(toks: list[Tok], i: int, prefix: list) -> tuple[int, list]:
    """Parses a use tree from toks[i]; returns the index after it and its leaves as
    (segments, alias, is_glob). Stops before `,` or `}` of an enclosing group, after `;`."""
    leaves = []
    segs = list(prefix)
    n = len(toks)
    if i < n and toks[i].text == "::":  # `use ::std::...`: another crate
        segs.append("::")
        i += 1
    while i < n:
        t = toks[i]
        if t.kind == "id":
            segs.append(t.text)
            i += 1
            if i < n and toks[i].text == "::":
                i += 1
                continue
            alias = None
            if i + 1 < n and toks[i].text == "as":
                alias = toks[i + 1].text
                i += 2
            leaves.append((tuple(segs), alias, False))
            break
        if t.text == "$" and i + 1 < n and toks[i + 1].text == "crate":
            i += 1
            continue
        if t.text == "*":
            leaves.append((tuple(segs), None, True))
            i += 1
            break
        if t.text == "{":
            i += 1
            while i < n and toks[i].text != "}":
                i, sub = _use_tree(toks, i, segs)
                leaves += sub
                if i < n and toks[i].text == ",":
                    i += 1
            i += 1
            break
        i += 1  # attributes or anything unexpected: skip
        break
    if not prefix:  # the outermost tree: run to the `;`
        while i < n and toks[i].text != ";":
            i += 1
        i += 1
    return i, leaves


def _absolute(mod: Module, segs, inline_depth: int):
    """Absolute segments (from the crate root) of a path written in `mod`, or None when the
    path leads into another crate."""
    segs = list(segs)
    if not segs or segs[0] == "::":
        return None
    head = segs[0]
    if head == "crate":
        return tuple(segs[1:])
    if head in ("self", "super"):
        base = list(mod.path)
        depth = inline_depth
        k = 0
        while k < len(segs) and segs[k] in ("self", "super"):
            if segs[k] == "super":
                if depth > 0:
                    depth -= 1
                elif base:
                    base.pop()
                else:
                    return None  # super of the root: not valid Rust
            k += 1
            if segs[k - 1] == "self":
                break
        # Inside an inline module `self` and its remaining `super`s stay in the file (folded in).
        return tuple(base) + tuple(segs[k:])
    if head in mod.children and inline_depth == 0:
        return tuple(mod.path) + tuple(segs)
    return None


# ---------------------------------------------------------------------------------------------
# The crate


class Crate:
    def __init__(self, src_dir: str, root_file: str | None = None):
        self.src_dir = src_dir
        if root_file is None:
            for cand in ("lib.rs", "main.rs"):
                if os.path.exists(os.path.join(src_dir, cand)):
                    root_file = os.path.join(src_dir, cand)
                    break
            else:
                raise LayerError(f"{src_dir} has neither lib.rs nor main.rs (give --root)")
        self.modules: dict[tuple, Module] = {}
        self.missing: list[str] = []
        self._load(ROOT, root_file, True)

    def _load(self, path: tuple, file: str, is_mod_rs: bool) -> None:
        if not os.path.exists(file):
            self.missing.append(f"{file} (module {name(path)})")
            return
        mod = Module(path, file)
        parse_module(mod, is_mod_rs)
        self.modules[path] = mod
        for child, f in mod.children.items():
            self._load(path + (child,), f, os.path.basename(f) == "mod.rs")

    def resolve(self, segs: tuple, seen=None) -> tuple:
        """The module that defines what the absolute path `segs` names."""
        seen = set() if seen is None else seen
        cur = ROOT
        for seg in segs:
            if cur + (seg,) in self.modules:
                cur = cur + (seg,)
                continue
            return self._item(cur, seg, seen)
        return cur

    def _item(self, mod_path: tuple, item: str, seen: set) -> tuple:
        if (mod_path, item) in seen:
            return mod_path
        seen.add((mod_path, item))
        mod = self.modules[mod_path]
        if item in mod.defined:
            return mod_path
        if item in mod.imports:
            return self.resolve(mod.imports[item], seen)
        for g in mod.globs:
            target = self.resolve(g, seen)
            if target in self.modules and target != mod_path:
                tm = self.modules[target]
                if item in tm.defined or item in tm.imports or tm.globs:
                    found = self._item(target, item, seen)
                    if item in self.modules[found].defined:
                        return found
        return mod_path

    def edges(self) -> dict:
        """{(a, b): (file, line, text)}: the first place a imports b."""
        out = {}
        for path, mod in sorted(self.modules.items()):
            for ref in mod.refs:
                target = self.resolve(ref.segs)
                if target != path and (path, target) not in out:
                    out[(path, target)] = (mod.file, ref.line, ref.text)
        return out


def name(path: tuple) -> str:
    return "crate" if path == ROOT else "::".join(path)


def cycles(nodes, edges) -> list[list]:
    """Strongly connected components of more than one node (Tarjan, iterative)."""
    adj = {v: [] for v in nodes}
    for a, b in edges:
        adj[a].append(b)
    index, low, on, stack, out = {}, {}, set(), [], []
    counter = [0]
    for root in sorted(nodes):
        if root in index:
            continue
        work = [(root, iter(sorted(adj[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(adj[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return sorted(out)


# ---------------------------------------------------------------------------------------------
# Layers


def read_layers(file: str, crate: Crate) -> tuple[dict, int, dict]:
    """{module path: layer index} for every module of the crate, from the layer file, the
    number of layers the file has (the root, when not named, is one above them), and for each
    module of an `apart:` layer the name on that line that covers it."""
    named: dict[tuple, int] = {}
    apart_layers: set[int] = set()
    problems = []
    with open(file, encoding="utf-8") as f:
        layer = 0
        for lineno, raw in enumerate(f, 1):
            line = raw.split("#", 1)[0].split()
            if not line:
                continue
            if line[0] == "apart:":
                apart_layers.add(layer)
                line = line[1:]
                if not line:
                    problems.append(f"{file}:{lineno}: `apart:` names no module")
            for word in line:
                path = ROOT if word == "crate" else tuple(word.split("::"))
                if path not in crate.modules:
                    problems.append(f"{file}:{lineno}: `{word}` is not a module of {crate.src_dir}")
                elif path in named:
                    problems.append(f"{file}:{lineno}: `{word}` is named twice")
                else:
                    named[path] = layer
            layer += 1
    top = layer
    out = {}
    apart = {}
    for path in crate.modules:
        cover = next((path[:k] for k in range(len(path), -1, -1) if path[:k] in named), None)
        if cover is not None:
            out[path] = named[cover]
            if named[cover] in apart_layers:
                apart[path] = cover
        elif path == ROOT:
            out[path] = top
        else:
            problems.append(f"{file}: module `{name(path)}` ({crate.modules[path].file}) is in no layer")
    if not named:
        problems.append(f"{file}: names no module")
    if problems:
        raise LayerError("\n".join(problems))
    return out, top, apart


# ---------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", help="the crate's source folder, e.g. crates/render/src")
    ap.add_argument("--layers", help="layer order file (lowest layer first)")
    ap.add_argument("--root", help="the crate root file (default SRC/lib.rs, else SRC/main.rs)")
    out = ap.add_mutually_exclusive_group()
    out.add_argument("--graph", action="store_true", help="print the edge list")
    out.add_argument("--dot", action="store_true", help="print the graph in Graphviz DOT")
    args = ap.parse_args(argv)

    if not os.path.isdir(args.src):
        print(f"error: {args.src} is not a folder", file=sys.stderr)
        return 2
    try:
        crate = Crate(args.src, args.root)
    except (LayerError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if crate.missing:
        for m in crate.missing:
            print(f"error: declared module file not found: {m}", file=sys.stderr)
        return 2
    edges = crate.edges()
    rel = lambda f: os.path.relpath(f)  # noqa: E731

    if args.graph:
        for (a, b), (f, line, text) in sorted(edges.items()):
            print(f"{name(a)} -> {name(b)}  {rel(f)}:{line}  {text}")
    elif args.dot:
        print("digraph modules {")
        for m in sorted(crate.modules):
            print(f'  "{name(m)}";')
        for a, b in sorted(edges):
            print(f'  "{name(a)}" -> "{name(b)}";')
        print("}")

    comps = cycles(crate.modules.keys(), edges.keys())
    in_cycles = sum(len(c) for c in comps)
    print(f"{args.src}: {len(crate.modules)} modules, {len(edges)} imports, "
          f"{len(comps)} cycles, {in_cycles} modules in cycles")
    for c in comps:
        members = set(c)
        print(f"cycle of {len(c)} modules: {', '.join(name(m) for m in c)}")
        for (a, b), (f, line, text) in sorted(edges.items()):
            if a in members and b in members:
                print(f"  {name(a)} -> {name(b)}  {rel(f)}:{line}  {text}")

    bad = 0
    if args.layers:
        try:
            layer, count, apart = read_layers(args.layers, crate)
        except (LayerError, OSError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        across = 0
        for (a, b), (f, line, text) in sorted(edges.items()):
            if layer[b] > layer[a]:
                bad += 1
                print(f"{rel(f)}:{line}: `{name(a)}` (layer {layer[a] + 1}) imports "
                      f"`{name(b)}` (layer {layer[b] + 1}), a higher layer: {text}")
            elif a in apart and b in apart and apart[a] != apart[b] and layer[a] == layer[b]:
                across += 1
                print(f"{rel(f)}:{line}: `{name(a)}` imports `{name(b)}`, kept apart from it "
                      f"(layer {layer[a] + 1} is `apart:`): {text}")
        print(f"{args.layers}: {count} layers, {bad} upward imports"
              + (f", {across} imports across an `apart:` layer" if apart else ""))
        bad += across
    return 1 if comps or bad else 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except BrokenPipeError:  # output piped into `head`
        sys.exit(1)
