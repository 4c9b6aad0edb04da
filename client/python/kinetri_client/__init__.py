"""Python client for the Kinetri proximity service (kinetri.v1).

Points and results are numpy arrays: positions as float64 arrays of shape
(n, 2); query results in CSR form (offsets, ids, distances). Chunking of large
uploads and step batches, and reassembly of streamed results, are hidden.

The generated stubs (kinetri/v1/kinetri_pb2*.py) are produced at build time
from proto/ (see client/python/CMakeLists.txt) and must be on sys.path.
"""

from kinetri_client.client import (SESSION_HEADER, Client, KinetriError,
                                   Neighbors, StepStream, new_session_id)

__all__ = ["Client", "Neighbors", "StepStream", "KinetriError",
           "SESSION_HEADER", "new_session_id"]
