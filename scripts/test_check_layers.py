"""Tests of check_layers.py on small synthetic crates written to a temporary folder.

Run: python3 -m unittest scripts/test_check_layers.py  (or: cd scripts && python3 -m unittest)
"""

import contextlib
import io
import os
import sys
import tempfile
import textwrap
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import check_layers  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class CrateTest(unittest.TestCase):
    def setUp(self):
        self._tmp = tempfile.TemporaryDirectory()
        self.src = os.path.join(self._tmp.name, "src")
        os.makedirs(self.src)

    def tearDown(self):
        self._tmp.cleanup()

    def write(self, files: dict):
        for rel, text in files.items():
            path = os.path.join(self.src, rel)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, "w", encoding="utf-8") as f:
                f.write(textwrap.dedent(text))

    def layers(self, text: str) -> str:
        path = os.path.join(self._tmp.name, "LAYERS")
        with open(path, "w", encoding="utf-8") as f:
            f.write(textwrap.dedent(text))
        return path

    def run_check(self, *args):
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = check_layers.main([self.src, *args])
        return rc, out.getvalue(), err.getvalue()

    def edges(self):
        crate = check_layers.Crate(self.src)
        return {(check_layers.name(a), check_layers.name(b)) for a, b in crate.edges()}


class Edges(CrateTest):
    def test_mod_declarations_alone_make_no_import(self):
        self.write({"lib.rs": "mod a;\npub mod b;\n", "a.rs": "pub fn f() {}\n", "b.rs": "\n"})
        self.assertEqual(self.edges(), set())

    def test_use_paths_and_paths_in_code_are_imports(self):
        self.write({
            "lib.rs": "mod a;\nmod b;\nmod c;\nmod d;\n",
            "a.rs": "use crate::b::{X, Y as Z};\nfn f() { crate::c::g(); }\n",
            "b.rs": "pub struct X;\npub struct Y;\n",
            "c.rs": "pub fn g() { super::d::h() }\n",
            "d.rs": "pub fn h() {}\n",
        })
        self.assertEqual(self.edges(), {("a", "b"), ("a", "c"), ("c", "d")})

    def test_comments_doc_links_strings_and_chars_are_not_code(self):
        self.write({
            "lib.rs": "mod a;\nmod b;\n",
            "a.rs": """\
                //! See [`crate::b::X`].
                /* use crate::b::X; /* nested */ crate::b::X */
                /// [`crate::b`]
                fn f<'a>(s: &'a str) -> (char, char, &'static str, &'static str) {
                    let _ = "crate::b::X";
                    ('\\'', 'b', r#"crate::b::X "quoted" "#, s)
                }
                """,
            "b.rs": "pub struct X;\n",
        })
        self.assertEqual(self.edges(), set())

    def test_a_path_is_resolved_through_re_exports_to_where_its_item_lives(self):
        self.write({
            "lib.rs": "mod a;\nmod b;\npub use b::Thing;\n",
            "a.rs": "use crate::Thing;\n",
            "b.rs": "pub struct Thing;\n",
        })
        # The root imports b (its re-export); a imports b, not the root.
        self.assertEqual(self.edges(), {("crate", "b"), ("a", "b")})

    def test_an_item_the_root_defines_is_an_import_of_the_root(self):
        self.write({
            "lib.rs": "mod a;\npub struct Control;\n",
            "a.rs": "fn f(_: crate::Control) {}\n",
        })
        self.assertEqual(self.edges(), {("a", "crate")})

    def test_inline_test_modules_are_part_of_their_file(self):
        self.write({
            "lib.rs": "mod a;\nmod b;\n",
            "a.rs": """\
                pub fn f() {}
                #[cfg(test)]
                mod tests {
                    use super::*;
                    use crate::b::helper;
                    #[test]
                    fn t() { super::f(); helper(); }
                }
                """,
            "b.rs": "pub fn helper() {}\n",
        })
        self.assertEqual(self.edges(), {("a", "b")})

    def test_nested_files_and_super_super(self):
        self.write({
            "lib.rs": "mod gpu;\nmod error;\n",
            "error.rs": "pub struct E;\n",
            "gpu/mod.rs": "mod ctx;\nmod kern;\npub use crate::error::E;\nuse kern::run;\n",
            "gpu/ctx.rs": "use super::E;\npub struct Ctx;\n",
            "gpu/kern.rs": """\
                use super::ctx::Ctx;
                pub fn run(_: Ctx) {}
                #[cfg(test)]
                mod tests {
                    use super::super::ctx::Ctx;
                }
                """,
        })
        # gpu::ctx names `super::E`, which gpu re-exports from error: an import of error.
        self.assertEqual(
            self.edges(),
            {("gpu", "error"), ("gpu", "gpu::kern"), ("gpu::ctx", "error"),
             ("gpu::kern", "gpu::ctx")},
        )

    def test_a_child_using_what_its_parent_defines_imports_the_parent(self):
        self.write({
            "lib.rs": "mod p;\n",
            "p/mod.rs": "mod child;\npub struct Shared;\npub fn top() { child::f() }\n",
            "p/child.rs": "use super::Shared;\npub fn f() { let _ = Shared; }\n",
        })
        self.assertEqual(self.edges(), {("p", "p::child"), ("p::child", "p")})
        rc, out, _ = self.run_check()
        self.assertEqual(rc, 1)
        self.assertIn("cycle of 2 modules: p, p::child", out)

    def test_non_mod_rs_children_and_path_attributes(self):
        self.write({
            "lib.rs": "mod a;\n#[path = \"other/impl_b.rs\"]\nmod b;\n",
            "a.rs": "mod inner;\npub fn f() { inner::g(); crate::b::h() }\n",
            "a/inner.rs": "pub fn g() {}\n",
            "other/impl_b.rs": "pub fn h() {}\n",
        })
        self.assertEqual(self.edges(), {("a", "a::inner"), ("a", "b")})

    def test_a_child_named_above_its_mod_line_and_visibility_paths(self):
        self.write({
            "lib.rs": "use a::A;\nmod a;\nmod b;\n",
            "a.rs": "pub struct A;\npub(in crate::b) fn hidden() {}\n",
            "b.rs": "pub fn f() { for _ in crate::a::A::iter() {} }\n",
        })
        # `pub(in crate::b)` names a module but imports nothing from it.
        self.assertEqual(self.edges(), {("crate", "a"), ("b", "a")})

    def test_a_folder_without_a_crate_root_is_an_error(self):
        rc, _, err = self.run_check()
        self.assertEqual(rc, 2)
        self.assertIn("neither lib.rs nor main.rs", err)

    def test_a_declared_module_without_a_file_is_an_error(self):
        self.write({"lib.rs": "mod gone;\n"})
        rc, _, err = self.run_check()
        self.assertEqual(rc, 2)
        self.assertIn("gone", err)


class Cycles(CrateTest):
    def test_every_cycle_is_listed_with_its_imports(self):
        self.write({
            "lib.rs": "mod a;\nmod b;\nmod c;\nmod d;\nmod e;\n",
            "a.rs": "use crate::b::B;\npub struct A;\n",
            "b.rs": "use crate::c::C;\npub struct B;\n",
            "c.rs": "use crate::a::A;\npub struct C;\n",
            "d.rs": "use crate::e::E;\npub struct D;\n",
            "e.rs": "use crate::d::D;\npub struct E;\n",
        })
        rc, out, _ = self.run_check()
        self.assertEqual(rc, 1)
        self.assertIn("2 cycles, 5 modules in cycles", out)
        self.assertIn("cycle of 3 modules: a, b, c", out)
        self.assertIn("cycle of 2 modules: d, e", out)
        self.assertIn("c -> a", out)
        self.assertRegex(out, r"c -> a  \S*c\.rs:1  use crate::a::A")

    def test_an_acyclic_crate_passes(self):
        self.write({
            "lib.rs": "mod a;\nmod b;\n",
            "a.rs": "use crate::b::B;\n",
            "b.rs": "pub struct B;\n",
        })
        rc, out, _ = self.run_check()
        self.assertEqual(rc, 0)
        self.assertIn("0 cycles", out)

    def test_graph_and_dot_print_the_edges(self):
        self.write({"lib.rs": "mod a;\nmod b;\n", "a.rs": "use crate::b::B;\n",
                    "b.rs": "pub struct B;\n"})
        _, out, _ = self.run_check("--graph")
        self.assertRegex(out, r"(?m)^a -> b  \S*a\.rs:1  use crate::b::B$")
        _, out, _ = self.run_check("--dot")
        self.assertIn('"a" -> "b";', out)
        self.assertIn("digraph", out)


class Layers(CrateTest):
    def setUp(self):
        super().setUp()
        self.write({
            "lib.rs": "pub mod error;\npub mod kernel;\npub mod method;\npub mod gpu;\n",
            "error.rs": "pub struct E;\n",
            "kernel.rs": "use crate::error::E;\npub fn k() {}\n",
            "method.rs": "use crate::kernel::k;\nuse crate::error::E;\n",
            "gpu/mod.rs": "mod kern;\npub use kern::run;\n",
            "gpu/kern.rs": "use crate::method;\npub fn run() {}\n",
        })

    def test_the_right_order_passes(self):
        rc, out, err = self.run_check("--layers", self.layers("error\nkernel\nmethod\ngpu\n"))
        self.assertEqual((rc, err), (0, ""))
        self.assertIn("4 layers, 0 upward imports", out)

    def test_modules_of_one_layer_may_import_each_other(self):
        rc, _, _ = self.run_check("--layers", self.layers("error\nkernel method # same layer\ngpu\n"))
        self.assertEqual(rc, 0)

    def test_an_import_of_a_higher_layer_fails_naming_the_place(self):
        rc, out, _ = self.run_check("--layers", self.layers("error\nmethod\nkernel\ngpu\n"))
        self.assertEqual(rc, 1)
        self.assertRegex(
            out,
            r"method\.rs:1: `method` \(layer 2\) imports `kernel` \(layer 3\), a higher layer",
        )
        self.assertIn("1 upward imports", out)

    def test_a_submodule_takes_its_ancestors_layer_unless_named(self):
        # gpu::kern imports method: fine while it sits with gpu, not when named below method.
        rc, _, _ = self.run_check("--layers", self.layers("error\nkernel\nmethod\ngpu\n"))
        self.assertEqual(rc, 0)
        rc, out, _ = self.run_check("--layers", self.layers("error\ngpu::kern\nkernel\nmethod\ngpu\n"))
        self.assertEqual(rc, 1)
        self.assertIn("`gpu::kern` (layer 2) imports `method` (layer 4)", out)

    def test_the_root_sits_on_top_unless_named(self):
        self.write({"kernel.rs": "use crate::error::E;\npub fn k() { crate::top() }\n",
                    "lib.rs": "pub mod error;\npub mod kernel;\npub mod method;\npub mod gpu;\n"
                              "pub fn top() {}\n"})
        rc, out, _ = self.run_check("--layers", self.layers("error\nkernel\nmethod\ngpu\n"))
        self.assertEqual(rc, 1)
        self.assertIn("`kernel` (layer 2) imports `crate` (layer 5)", out)
        rc, _, _ = self.run_check("--layers", self.layers("error\ncrate kernel\nmethod\ngpu\n"))
        self.assertEqual(rc, 0)

    def test_a_layer_file_that_does_not_match_the_crate_cannot_pass(self):
        cases = {
            "a module that does not exist": ("error\nkernel\nmethod\ngpu\nwindow\n", "`window` is not a module"),
            "a module in no layer": ("error\nkernel\ngpu\n", "module `method`"),
            "a module named twice": ("error\nkernel\nmethod\ngpu kernel\n", "`kernel` is named twice"),
            "an empty file": ("# nothing\n\n", "names no module"),
        }
        for what, (text, message) in cases.items():
            with self.subTest(what):
                rc, _, err = self.run_check("--layers", self.layers(text))
                self.assertEqual(rc, 2)
                self.assertIn(message, err)

    def test_a_missing_layer_file_is_an_error(self):
        rc, _, err = self.run_check("--layers", os.path.join(self._tmp.name, "nope"))
        self.assertEqual(rc, 2)
        self.assertIn("nope", err)

    def test_the_modules_of_an_apart_layer_may_not_import_each_other(self):
        # method imports kernel: fine in one plain layer, not in one `apart:` layer; what each
        # covers (gpu::kern under gpu) is kept apart too, and the layers below stay open.
        rc, out, _ = self.run_check("--layers", self.layers("error\napart: kernel method\ngpu\n"))
        self.assertEqual(rc, 1)
        self.assertRegex(out, r"method\.rs:1: `method` imports `kernel`, kept apart from it")
        self.assertIn("1 imports across an `apart:` layer", out)
        rc, out, _ = self.run_check("--layers", self.layers("error\nkernel\napart: method gpu\n"))
        self.assertEqual(rc, 1)
        self.assertIn("`gpu::kern` imports `method`, kept apart from it", out)
        self.write({"gpu/kern.rs": "use crate::kernel::k;\npub fn run() {}\n"})
        rc, out, _ = self.run_check("--layers", self.layers("error\nkernel\napart: method gpu\n"))
        self.assertEqual(rc, 0, out)
        self.assertIn("0 imports across an `apart:` layer", out)

    def test_an_apart_line_naming_nothing_cannot_pass(self):
        rc, _, err = self.run_check("--layers", self.layers("error\nkernel\napart:\nmethod gpu\n"))
        self.assertEqual(rc, 2)
        self.assertIn("`apart:` names no module", err)

    def test_a_cycle_fails_even_within_one_layer(self):
        self.write({"error.rs": "pub struct E;\nfn f() { crate::kernel::k() }\n"})
        rc, out, _ = self.run_check("--layers", self.layers("error kernel\nmethod\ngpu\n"))
        self.assertEqual(rc, 1)
        self.assertIn("cycle of 2 modules: error, kernel", out)


class ThisRepository(unittest.TestCase):
    def test_the_cli_keeps_its_layers(self):
        src = os.path.join(REPO, "crates", "cli", "src")
        layers = os.path.join(REPO, "crates", "cli", "LAYERS")
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            rc = check_layers.main([src, "--layers", layers])
        self.assertEqual(rc, 0, out.getvalue())
        self.assertIn("0 imports across an `apart:` layer", out.getvalue())
        crate = check_layers.Crate(src)
        self.assertGreater(len(crate.modules), 30)

    def test_render_keeps_its_layers(self):
        src = os.path.join(REPO, "crates", "render", "src")
        layers = os.path.join(REPO, "crates", "render", "LAYERS")
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            rc = check_layers.main([src, "--layers", layers])
        self.assertEqual(rc, 0, out.getvalue())
        # Not vacuous: the crate has its modules and their imports.
        crate = check_layers.Crate(src)
        self.assertGreater(len(crate.modules), 20)
        self.assertGreater(len(crate.edges()), 80)


if __name__ == "__main__":
    unittest.main()
