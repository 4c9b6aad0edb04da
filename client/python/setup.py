"""Builds the kinetri_client package with its gRPC stubs generated from
proto/kinetri/v1/kinetri.proto at build time (protoc and grpc_python_plugin
from Debian's protobuf-compiler and protobuf-compiler-grpc; no PyPI).

The proto is looked up in $KINETRI_PROTO_DIR, then in ../../proto (the
source tree). The stubs go to kinetri_client/_pb with the import between
them made package-relative; protoc's .pyi stubs give the messages types.
"""

import os
import shutil
import subprocess
import tempfile

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = os.path.dirname(os.path.abspath(__file__))
PROTO = os.path.join("kinetri", "v1", "kinetri.proto")


def proto_dir() -> str:
    for d in (os.environ.get("KINETRI_PROTO_DIR"),
              os.path.join(HERE, "..", "..", "proto")):
        if d and os.path.exists(os.path.join(d, PROTO)):
            return os.path.abspath(d)
    raise RuntimeError("kinetri.proto not found: set KINETRI_PROTO_DIR to "
                       "the proto/ directory of the Kinetri source tree")


def tool(name: str) -> str:
    path = shutil.which(name)
    if not path:
        raise RuntimeError(f"{name} not found (Debian: apt-get install "
                           "protobuf-compiler protobuf-compiler-grpc)")
    return path


def generate(out: str) -> None:
    """kinetri_pb2.py, kinetri_pb2.pyi and kinetri_pb2_grpc.py in `out`."""
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [tool("protoc"), f"--proto_path={proto_dir()}",
             f"--python_out={tmp}", f"--pyi_out={tmp}",
             f"--grpc_python_out={tmp}",
             f"--plugin=protoc-gen-grpc_python={tool('grpc_python_plugin')}",
             PROTO], check=True)
        os.makedirs(out, exist_ok=True)
        gen = os.path.join(tmp, "kinetri", "v1")
        for name in ("kinetri_pb2.py", "kinetri_pb2.pyi",
                     "kinetri_pb2_grpc.py"):
            with open(os.path.join(gen, name)) as f:
                text = f.read()
            text = text.replace("from kinetri.v1 import kinetri_pb2",
                                "from kinetri_client._pb import kinetri_pb2")
            with open(os.path.join(out, name), "w") as f:
                f.write(text)
        with open(os.path.join(out, "__init__.py"), "w") as f:
            f.write('"""Generated from kinetri/v1/kinetri.proto."""\n')


class BuildPyWithStubs(build_py):
    def run(self):
        super().run()
        generate(os.path.join(self.build_lib, "kinetri_client", "_pb"))


setup(cmdclass={"build_py": BuildPyWithStubs})
