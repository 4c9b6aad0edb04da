"""Checks deploy/ as far as possible without Docker or Kubernetes: every file
parses, the image builds with the same setup script CI uses, and every metric
the dashboard and manifests rely on is one the server defines."""

import json
import pathlib
import re
import sys
import unittest

import yaml

ROOT = pathlib.Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"


class DeployFilesTest(unittest.TestCase):
    def test_yaml_files_parse(self):
        for path in DEPLOY.rglob("*.y*ml"):
            with self.subTest(path=str(path)):
                docs = list(yaml.safe_load_all(path.read_text()))
                self.assertTrue(docs and all(d is not None for d in docs))

    def test_compose_services(self):
        compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
        self.assertEqual(set(compose["services"]),
                         {"kinetri", "prometheus", "grafana"})
        self.assertEqual(compose["services"]["kinetri"]["build"]["dockerfile"],
                         "deploy/Dockerfile")

    def test_dockerfile_uses_the_ci_setup_script(self):
        text = (DEPLOY / "Dockerfile").read_text()
        self.assertIn("bash scripts/setup.sh", text)
        self.assertIn("FROM debian:bookworm", text)
        self.assertTrue((ROOT / "scripts" / "setup.sh").exists())

    def test_cuda_variant(self):
        text = (DEPLOY / "Dockerfile.cuda").read_text()
        self.assertIn("bash scripts/setup.sh", text)
        self.assertIn("-DKINETRI_CUDA=ON", text)
        docs = list(yaml.safe_load_all(
            (DEPLOY / "k8s-cuda" / "kinetri-cuda.yaml").read_text()))
        sts = next(d for d in docs if d["kind"] == "StatefulSet")
        container = sts["spec"]["template"]["spec"]["containers"][0]
        self.assertEqual(container["resources"]["limits"]["nvidia.com/gpu"], 1)
        self.assertEqual(container["image"], "kinetri-server:cuda")

    def test_k8s_probes_use_grpc_health(self):
        docs = list(yaml.safe_load_all((DEPLOY / "k8s" / "kinetri.yaml").read_text()))
        kinds = {d["kind"] for d in docs}
        self.assertEqual(kinds, {"Service", "StatefulSet"})
        service = next(d for d in docs if d["kind"] == "Service")
        self.assertEqual(service["spec"]["clusterIP"], "None")
        sts = next(d for d in docs if d["kind"] == "StatefulSet")
        container = sts["spec"]["template"]["spec"]["containers"][0]
        self.assertEqual(container["readinessProbe"]["grpc"]["port"], 50051)
        self.assertEqual(container["livenessProbe"]["grpc"]["port"], 50051)

    def test_dashboard_metrics_exist(self):
        dash = json.loads((DEPLOY / "grafana" / "dashboards" / "kinetri.json").read_text())
        defined = set(re.findall(r'Name\("([a-z_]+)"\)',
                                 (ROOT / "server" / "metrics.cc").read_text()))
        self.assertTrue(defined)
        for panel in dash["panels"]:
            for target in panel["targets"]:
                for name in re.findall(r"\b(kinetri_[a-z_]+|grpc_server_[a-z_]+)",
                                       target["expr"]):
                    base = re.sub(r"_(bucket|count|sum)$", "", name)
                    self.assertIn(base, defined, f"{panel['title']}: {name}")


if __name__ == "__main__":
    unittest.main()
