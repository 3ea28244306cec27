"""kdrt for Python: the kdrt ray-tracing server from numpy.

    import kdrt
    client = kdrt.Client("http://127.0.0.1:8080")
    mesh = client.upload("bunny.obj")                 # or client.upload(vertices, triangles)
    hits = client.cast_rays(mesh, rays)               # rays: float32 (..., 6) or (..., 8)
    depth = hits["t_hit"]                             # shaped like rays[..., 0], inf on a miss
    scene = kdrt.Scene(client)                        # many meshes placed by transforms
    g = scene.add_triangles(mesh, transform=T)        # -> geometry id; scene.cast_rays(rays)

Depends on numpy only; HTTP goes through the standard library's http.client. See README.md.
"""

from ._errors import Error
from ._scan import LIDAR_POINT_DTYPE
from ._wire import FEATURES, NO_HIT
from .client import Client, Job, Mesh
from .png import read_png, write_png
from .scene import NO_GEOMETRY, Scene

for _public in (Error, Client, Job, Mesh, Scene):
    _public.__module__ = "kdrt"  # kdrt.Error in tracebacks, not kdrt._errors.Error
del _public

__version__ = "0.1.0"
__all__ = ["Client", "Error", "FEATURES", "Job", "LIDAR_POINT_DTYPE", "Mesh", "NO_GEOMETRY",
           "NO_HIT", "Scene", "read_png", "write_png", "__version__"]
