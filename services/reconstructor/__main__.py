import sys

from services.reconstructor.service import ReconstructorService
from shared.runner import run

sys.exit(run(ReconstructorService))
