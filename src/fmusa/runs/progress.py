"""A progress bar for stages of many runs."""
from __future__ import annotations


def progress_bar(total: int, desc: str, enabled: bool):
    if not enabled or total < 50:
        return None
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="run", leave=False, mininterval=0.5)

