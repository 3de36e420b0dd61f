import sys

from services.planner.service import PlannerService
from shared.runner import run

sys.exit(run(PlannerService))
