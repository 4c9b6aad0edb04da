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
                         {"kinetri-0", "kinetri-1", "kinetri-2", "proxy",
                          "prometheus", "grafana"})
        for i in range(3):
            k = compose["services"][f"kinetri-{i}"]
            self.assertEqual(k["build"]["dockerfile"], "deploy/Dockerfile")
            # Its own volume, and the name the proxy resolves.
            self.assertIn(f"kinetri-data-{i}:/var/lib/kinetri", k["volumes"])
            self.assertEqual(k["networks"]["default"]["aliases"],
                             [f"kinetri-{i}.kinetri"])
        proxy = compose["services"]["proxy"]
        self.assertEqual(proxy["environment"]["KINETRI_REPLICA_DOMAIN"],
                         "kinetri")
        self.assertIn("./proxy/haproxy.cfg:/usr/local/etc/haproxy/haproxy.cfg:ro",
                      proxy["volumes"])
        prom = yaml.safe_load((DEPLOY / "prometheus" / "prometheus.yml").read_text())
        self.assertEqual(prom["scrape_configs"][0]["static_configs"][0]["targets"],
                         [f"kinetri-{i}:9464" for i in range(3)])

    def test_proxy_routes_by_session(self):
        """One replica per session: HAProxy hashes the header every client
        sets, consistently, and never moves a key to another replica."""
        cfg = (DEPLOY / "proxy" / "haproxy.cfg").read_text()
        self.assertIn("balance hdr(kinetri-session)", cfg)
        self.assertIn("hash-type consistent", cfg)
        self.assertNotRegex(cfg, r"(?m)^\s*option redispatch")
        self.assertNotRegex(cfg, r"(?m)^\s*server .* check")
        servers = re.findall(r'(?m)^\s*server (kinetri-\d+) "kinetri-\d+\.'
                             r'\$\{KINETRI_REPLICA_DOMAIN\}:50051" id (\d+)$', cfg)
        self.assertEqual(servers, [(f"kinetri-{i}", str(i + 1)) for i in range(3)])
        docs = list(yaml.safe_load_all((DEPLOY / "k8s" / "kinetri.yaml").read_text()))
        sts = next(d for d in docs if d["kind"] == "StatefulSet")
        self.assertEqual(sts["spec"]["replicas"], len(servers))
        pdb = next(d for d in docs if d["kind"] == "PodDisruptionBudget")
        self.assertEqual(pdb["spec"]["maxUnavailable"], 1)
        for client in ("client/cpp/kinetri_client.h",
                       "client/python/kinetri_client/_common.py",
                       "client/node/index.js"):
            self.assertIn('"kinetri-session"' if client.endswith(".h") or
                          client.endswith(".py") else "'kinetri-session'",
                          (ROOT / client).read_text(), client)

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
        # Sessions stay on the CPU executor (--device=auto), faster on the
        # GPUs measured (docs/DEVICE.md); the manifest says how to change it.
        self.assertNotIn("--device=cuda", container["args"])
        self.assertIn("add --device=cuda", (DEPLOY / "k8s-cuda" /
                                            "kinetri-cuda.yaml").read_text())

    def test_k8s_probes_use_grpc_health(self):
        docs = list(yaml.safe_load_all((DEPLOY / "k8s" / "kinetri.yaml").read_text()))
        kinds = {d["kind"] for d in docs}
        self.assertEqual(kinds, {"Service", "StatefulSet", "Deployment",
                                 "PodDisruptionBudget"})
        service = next(d for d in docs if d["kind"] == "Service"
                       and d["metadata"]["name"] == "kinetri")
        self.assertEqual(service["spec"]["clusterIP"], "None")
        sts = next(d for d in docs if d["kind"] == "StatefulSet")
        container = sts["spec"]["template"]["spec"]["containers"][0]
        # Probes on the plaintext health-only port (kubelet gRPC probes
        # cannot speak TLS).
        self.assertEqual(container["readinessProbe"]["grpc"]["port"], 8081)
        self.assertEqual(container["livenessProbe"]["grpc"]["port"], 8081)

    def test_secure_by_default(self):
        """TLS + tokens from mounted secrets, a numeric non-root user, a
        read-only root filesystem (docs/SECURITY.md)."""
        for name in ("Dockerfile", "Dockerfile.cuda"):
            text = (DEPLOY / name).read_text()
            for flag in ("--tls_cert=/etc/kinetri/tls/tls.crt",
                         "--tls_key=/etc/kinetri/tls/tls.key",
                         "--auth_tokens_file=/etc/kinetri/auth/tokens",
                         "--health_listen=0.0.0.0:8081",
                         "--data_dir=/var/lib/kinetri"):
                self.assertIn(flag, text, name)
            self.assertRegex(text, r"(?m)^USER 10001:10001$")
        for path in (DEPLOY / "k8s" / "kinetri.yaml",
                     DEPLOY / "k8s-cuda" / "kinetri-cuda.yaml"):
            docs = list(yaml.safe_load_all(path.read_text()))
            pod = next(d for d in docs
                       if d["kind"] == "StatefulSet")["spec"]["template"]["spec"]
            c = pod["containers"][0]
            sc = c["securityContext"]
            self.assertTrue(sc["runAsNonRoot"] and sc["readOnlyRootFilesystem"])
            self.assertEqual(sc["runAsUser"], 10001)
            self.assertFalse(sc["allowPrivilegeEscalation"])
            mounts = {m["mountPath"]: m["name"] for m in c["volumeMounts"]}
            secrets = {v["name"]: v["secret"]["secretName"]
                       for v in pod["volumes"]}
            self.assertEqual(secrets[mounts["/etc/kinetri/tls"]], "kinetri-tls")
            self.assertEqual(secrets[mounts["/etc/kinetri/auth"]],
                             "kinetri-tokens")
            # Sessions persist on the replica's own volume.
            sts = next(d for d in docs if d["kind"] == "StatefulSet")
            claims = {t["metadata"]["name"]
                      for t in sts["spec"]["volumeClaimTemplates"]}
            self.assertIn(mounts["/var/lib/kinetri"], claims)
        compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
        for i in range(3):
            k = compose["services"][f"kinetri-{i}"]
            self.assertTrue(k["read_only"])
            self.assertEqual(k["user"], "10001:10001")
            self.assertIn("./secrets/tls:/etc/kinetri/tls:ro", k["volumes"])

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
