import sys

from services.mapper.service import MapperService
from shared.runner import run

sys.exit(run(MapperService))
