"""Write the suite files of wl_env/suites/ from their definitions (wl_env.suites.suite_files).

    python scripts/make_suites.py            # rewrite the packaged suite files
    python scripts/make_suites.py --check    # exit 1 if a packaged file differs from its definition
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # (this checkout's packages, not an installed copy)

from wl_env.atomic_io import write_atomic  # noqa: E402
from wl_env.suites import FOLDER, suite_files  # noqa: E402

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if a packaged file is out of date")
    from agents.train_cli import refuse_repeated_options

    refuse_repeated_options(ap)  # (argparse kept the last of an option given twice, without a word)
    args = ap.parse_args()
    stale = []
    for name, data in suite_files().items():
        path, text = FOLDER / f"{name}.json", json.dumps(data, indent=1) + "\n"
        if args.check:
            if not path.is_file() or path.read_text() != text:
                stale.append(path)
            continue
        write_atomic(path, text)
        print(f"wrote {path} ({len(data.get('scenarios', []))} scenarios)")
    for path in stale:
        print(f"{path} differs from its definition (python scripts/make_suites.py rewrites it)", file=sys.stderr)
    sys.exit(1 if stale else 0)
