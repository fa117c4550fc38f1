"""GET /presets: the named systems a spec may use."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import CurrentCaller
from svrobs_core.systems import PRESETS, resolve_system

router = APIRouter(tags=["presets"])


@router.get("/presets")
def list_presets(caller: CurrentCaller) -> list[dict]:
    """System presets (docs/science.md#9-the-papers-section-6-as-a-preset) with their matrices
    and noise levels."""
    out = []
    for name in sorted(PRESETS):
        s = resolve_system(name, field="systems[0]")
        out.append({"name": name, **{k: v for k, v in s.to_dict().items() if k != "name"}})
    return out
