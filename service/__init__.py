"""HTTP service and command line of omnisplat.

Entry points: :func:`service.app.create_app` (the FastAPI app) and :func:`service.cli.main`
(the ``omnisplat`` command). Nothing here imports torch at import time.
"""

__version__ = "0.1.0"
