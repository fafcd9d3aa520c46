"""Every name a subpackage exports has an entry in the built API reference.

Usage: python .ci/check_api_pages.py SITE_DIR (after ``mkdocs build --strict``).
"""

from __future__ import annotations

import importlib
import pkgutil
import re
import sys
from pathlib import Path

import prognos_torch

site = Path(sys.argv[1])
pages = [m.name for m in pkgutil.iter_modules(prognos_torch.__path__) if m.ispkg]
pages += ["io", "metrics"]
missing = []
for name in pages:
    page = site / name / "index.html"
    if not page.is_file():
        missing.append(f"{name}: no page (add docs/api/{name}.md to mkdocs.yml)")
        continue
    ids = set(re.findall(r'id="([^"]+)"', page.read_text(encoding="utf-8")))
    mod = importlib.import_module(f"prognos_torch.{name}")
    for sym in getattr(mod, "__all__", []):
        if f"prognos_torch.{name}.{sym}" not in ids and not any(i.endswith(f".{sym}") for i in ids):
            missing.append(f"{name}.{sym}")
if missing:
    print("API reference lacks: " + ", ".join(missing))
    sys.exit(1)
print(f"API reference: {len(pages)} pages, every exported name present")
