"""Run the Khronos glTF-Validator (npm package ``gltf-validator``) on an exported .glb or .gltf.

The validator is JavaScript; it runs through ``node`` from a local npm prefix, by default
``.cache/npm`` in the repository (``make verify-export`` installs it there: ``npm install --prefix
.cache/npm gltf-validator``), or the directory named by ``FITME_GLTF_VALIDATOR`` (the package's own
folder). It is a verification tool, not a dependency of fitme: ``find_validator`` returns None when
node or the package is missing, and callers skip.

    python -m fitme_cli.export.validate OUT/head.glb     # prints the summary; exit 1 on any error
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ValidatorReport", "find_validator", "validate_gltf", "NPM_PREFIX"]

NPM_PREFIX = Path(__file__).resolve().parents[2] / ".cache" / "npm"

# reads the asset and its external resources (.bin, images) relative to it, prints the JSON report
_SCRIPT = r"""
const v = require(process.argv[1]);
const fs = require('fs'), path = require('path');
const file = process.argv[2];
const base = path.dirname(file);
v.validateBytes(new Uint8Array(fs.readFileSync(file)), {
  uri: path.basename(file),
  maxIssues: 0,
  externalResourceFunction: (uri) => new Promise((resolve, reject) => {
    fs.readFile(path.resolve(base, decodeURIComponent(uri)), (err, d) => err ? reject(err.toString()) : resolve(new Uint8Array(d)));
  }),
}).then((r) => process.stdout.write(JSON.stringify(r)))
  .catch((e) => { process.stderr.write(String(e)); process.exit(2); });
"""


@dataclass(frozen=True)
class ValidatorReport:
    """The validator's counts, its messages (dicts with code, message, severity 0-3, pointer) and its
    version; ``raw``: the full report."""

    errors: int
    warnings: int
    infos: int
    hints: int
    messages: list[dict]
    version: str
    raw: dict

    def summary(self) -> str:
        return (f"glTF-Validator {self.version}: {self.errors} errors, {self.warnings} warnings, "
                f"{self.infos} infos, {self.hints} hints")


def find_validator() -> tuple[str, Path] | None:
    """(node executable, gltf-validator package directory), or None if either is missing."""
    node = shutil.which("node")
    env = os.environ.get("FITME_GLTF_VALIDATOR")
    pkg = Path(env) if env else NPM_PREFIX / "node_modules" / "gltf-validator"
    if node is None or not (pkg / "package.json").is_file():
        return None
    return node, pkg


def validate_gltf(path: Path, timeout_s: float = 120.0) -> ValidatorReport:
    """Validate ``path`` (.glb or .gltf with its files beside it). RuntimeError when the validator is
    not installed or fails to run (not when the asset has issues: those are in the report)."""
    found = find_validator()
    if found is None:
        raise RuntimeError(f"gltf-validator is not installed (need node and {NPM_PREFIX}/node_modules/gltf-validator)")
    node, pkg = found
    r = subprocess.run([node, "-e", _SCRIPT, str(pkg.resolve()), str(Path(path).resolve())], capture_output=True,
                       text=True, timeout=timeout_s)
    if r.returncode != 0:
        raise RuntimeError(f"gltf-validator failed (exit {r.returncode}): {r.stderr.strip()[:500]}")
    rep = json.loads(r.stdout)
    iss = rep.get("issues", {})
    return ValidatorReport(int(iss.get("numErrors", -1)), int(iss.get("numWarnings", -1)), int(iss.get("numInfos", -1)),
                           int(iss.get("numHints", -1)), list(iss.get("messages", [])), str(rep.get("validatorVersion", "?")), rep)


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: python -m fitme_cli.export.validate FILE.glb|FILE.gltf ...", file=sys.stderr)
        return 2
    worst = 0
    for p in argv:
        rep = validate_gltf(Path(p))
        print(f"{p}: {rep.summary()}")
        for m in rep.messages:
            print(f"  [{('error', 'warning', 'info', 'hint')[m.get('severity', 0)]}] {m.get('code')}: {m.get('message')} "
                  f"({m.get('pointer', '')})")
        worst = max(worst, 1 if rep.errors else 0)
    return worst


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
