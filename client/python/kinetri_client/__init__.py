"""Python client for the Kinetri proximity service (kinetri.v1).

Points and results are numpy arrays: positions as float64 arrays of shape
(n, 2); query results in CSR form (offsets, ids, distances). Chunking of large
uploads and step batches, and reassembly of streamed results, are hidden.
`Client` is synchronous; `kinetri_client.aio.AsyncClient` is the same for
asyncio.

Installed as a package (`pip install ./client/python`), the generated stubs
are inside it (kinetri_client._pb); in the source tree they come from the
build (build/client/python/gen on sys.path).
"""

from kinetri_client._common import (SESSION_HEADER, Export, KinetriError,
                                    Neighbors, new_session_id)
from kinetri_client.client import Client, StepStream

__version__ = "0.1.0"
__all__ = ["Client", "Neighbors", "Export", "StepStream", "KinetriError",
           "SESSION_HEADER", "new_session_id"]
