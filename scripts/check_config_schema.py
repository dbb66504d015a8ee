#!/usr/bin/env python3
"""`dioptra config schema` checked by a validator we did not write (python-jsonschema):
every example rig config validates against it, and configs the daemon refuses for their
shape (an unknown key, a wrong type, a value not among a key's choices) do not.

    python3 scripts/check_config_schema.py --binary target/debug/dioptra
"""
import argparse
import glob
import json
import os
import subprocess
import sys
import tomllib

import jsonschema

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--binary", default=os.path.join(ROOT, "target/debug/dioptra"))
    args = ap.parse_args()
    schema = json.loads(subprocess.check_output([args.binary, "config", "schema"]))
    validator_cls = jsonschema.validators.validator_for(schema)
    validator_cls.check_schema(schema)
    validator = validator_cls(schema)

    examples = sorted(glob.glob(os.path.join(ROOT, "crates/cli/examples/*.toml")))
    assert examples, "no example rigs found"
    failures = []
    for path in examples:
        with open(path, "rb") as f:
            config = tomllib.load(f)
        errors = sorted(validator.iter_errors(config), key=str)
        if errors:
            failures.append(f"{path}: {errors[0].message} at {list(errors[0].path)}")
        else:
            print(f"ok   {os.path.relpath(path, ROOT)} validates")

    with open(examples[0], "rb") as f:
        base = tomllib.load(f)
    refused = {
        "an unknown top-level key": dict(base, lens_rnage=1),
        "an unknown key in [eye]": dict(base, eye=dict(base["eye"], ipd_nm=63)),
        "a string for eye.pupil_mm": dict(base, eye=dict(base["eye"], pupil_mm="four")),
        "an unknown display.kind": dict(base, display=dict(base["display"], kind="hologram")),
        "an unknown lens driver": dict(
            base, devices=dict(base["devices"], lens=dict(base["devices"]["lens"], driver="x"))
        ),
    }
    for what, config in refused.items():
        if validator.is_valid(config):
            failures.append(f"the schema takes {what}, which the daemon refuses")
        else:
            print(f"ok   the schema refuses {what}")
    if failures:
        print("\n".join(failures), file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
