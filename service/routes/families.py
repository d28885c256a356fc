"""``GET /families``: the block families the cell knows and which of its blocks are of each.

The dashboard builds its tuning cards and plots from this answer: a family with blocks has
its resource ``/{section}`` (list, read and tune its blocks); one without has none.
"""

from fastapi import APIRouter

from ..deps import CellDep
from ..schemas import FamilyOut

router = APIRouter(tags=["blocks"])


@router.get("/families", response_model=list[FamilyOut], name="list block families")
def list_families(cell: CellDep) -> list[FamilyOut]:
    """Every registered block family (filters, controllers, observers, and a plugin's):
    its section, description, example PATCH bodies and the names of the cell's blocks."""
    return [FamilyOut(**f) for f in cell.families()]
