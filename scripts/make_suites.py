"""Write the suite files of wl_env/suites/ from their definitions (wl_env.suites.suite_files).

    python scripts/make_suites.py
"""

import json

from wl_env.atomic_io import write_atomic
from wl_env.suites import FOLDER, suite_files

if __name__ == "__main__":
    for name, data in suite_files().items():
        write_atomic(FOLDER / f"{name}.json", json.dumps(data, indent=1) + "\n")
        print(f"wrote {FOLDER / f'{name}.json'} ({len(data.get('scenarios', []))} scenarios)")
