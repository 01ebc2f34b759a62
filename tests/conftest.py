"""Suite-wide settings: FastAPI's TestClient sends ``Host: testserver``, which the REST guard
(services.kit.guard) must accept in tests as it accepts 127.0.0.1 and localhost."""

import os

os.environ.setdefault("AOI3D_ALLOWED_HOSTS", "127.0.0.1,localhost,::1,testserver")
