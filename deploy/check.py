"""Checks Furnace's deployment files against each other, the Kubernetes schemas and the binary.

    python deploy/check.py --furnace target/debug/furnace --metrics METRICS.txt

Run by `tests/farm_processes.rs` (deploy_files_...) with the venv `.ci/run` makes
(deploy/requirements.txt). It renders each Kustomize overlay (resources only, the one feature
the manifests use; anything else in a kustomization is refused here), validates every object
whose kind Kubernetes defines against its schema (kubernetes-validate, strict: unknown fields
fail), and checks what no schema can: names that must match across objects, the token's Secret,
the autoscalers' target and metric, the drain, the Dockerfile's targets, user and health
checks, Compose's services, and that every metric the Grafana dashboard queries is one the
coordinator exports and every flag the files pass is one the binary accepts.
"""
import argparse
import json
import os
import re
import subprocess
import sys

import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
K8S_VERSION = "1.34.0"
UID = 10001
PORT = 8640
failures = []


def check(ok, msg):
    if not ok:
        failures.append(msg)
    return ok


def kustomize(folder):
    """Objects of a kustomization whose only field with content is `resources`."""
    k = yaml.safe_load(open(os.path.join(folder, "kustomization.yaml")))
    extra = set(k) - {"apiVersion", "kind", "resources"}
    if extra:
        raise SystemExit(f"{folder}: kustomization fields {sorted(extra)} are not rendered by this check")
    objs = []
    for r in k["resources"]:
        path = os.path.normpath(os.path.join(folder, r))
        if os.path.isdir(path):
            objs += kustomize(path)
        else:
            objs += [d for d in yaml.safe_load_all(open(path)) if d]
    return objs


def by_kind(objs, kind):
    return {o["metadata"]["name"]: o for o in objs if o["kind"] == kind}


def env_of(container):
    return {e["name"]: e for e in container.get("env", [])}


def flags_of(furnace, sub):
    out = subprocess.run([furnace, sub, "--help"], capture_output=True, text=True, check=True).stdout
    return set(re.findall(r"(--[a-z][a-z-]*)", out)), set(re.findall(r"\[env: ([A-Z_]+)=", out))


def check_args(furnace, where, args, env=()):
    """`args` (after the program name) use a subcommand and flags the binary has; `env`
    names variables it reads for that subcommand."""
    if not check(args, f"{where}: no command"):
        return
    sub = args[0]
    try:
        flags, envs = flags_of(furnace, sub)
    except subprocess.CalledProcessError:
        check(False, f"{where}: furnace has no subcommand '{sub}'")
        return
    for a in args[1:]:
        if a.startswith("--"):
            check(a.split("=")[0] in flags, f"{where}: 'furnace {sub}' has no flag {a}")
    for e in env:
        if e.startswith("FURNACE_"):
            check(e in envs, f"{where}: 'furnace {sub}' does not read {e}")


def check_kubernetes(furnace):
    import kubernetes_validate  # here, so that try-runtime.sh can use the Dockerfile parser without it

    overlays = {}
    for name in ["keda", "hpa"]:
        objs = kustomize(os.path.join(ROOT, "deploy/kubernetes/overlays", name))
        overlays[name] = objs
        for o in objs:
            if o["apiVersion"].startswith("keda.sh/"):
                continue
            try:
                kubernetes_validate.validate(o, K8S_VERSION, strict=True)
            except kubernetes_validate.ValidationError as e:
                check(False, f"{name}: {o['kind']} {o['metadata']['name']}: {e.message} at {list(e.path)}")
        sts = by_kind(objs, "StatefulSet").get("furnace-coordinator")
        dep = by_kind(objs, "Deployment").get("furnace-worker")
        svc = by_kind(objs, "Service").get("furnace-coordinator")
        if not (check(sts, "no coordinator StatefulSet") and check(dep, "no worker Deployment")
                and check(svc, "no coordinator Service")):
            continue
        # The coordinator: one replica, its data on a claim, reachable through the Service.
        spec = sts["spec"]
        pod = spec["template"]["spec"]
        (c,) = pod["containers"]
        check(spec["replicas"] == 1, "the coordinator must have one replica (one SQLite owner)")
        check(spec["serviceName"] == svc["metadata"]["name"], "StatefulSet serviceName is not the Service")
        labels = spec["template"]["metadata"]["labels"]
        check(all(labels.get(k) == v for k, v in svc["spec"]["selector"].items()), "the Service selects no coordinator")
        claims = {t["metadata"]["name"]: t for t in spec.get("volumeClaimTemplates", [])}
        env = env_of(c)
        data = env.get("FURNACE_DATA_DIR", {}).get("value")
        mounts = {m["name"]: m["mountPath"] for m in c.get("volumeMounts", [])}
        check(any(mounts.get(n) == data for n in claims), "FURNACE_DATA_DIR is not on a persistent volume claim")
        for t in claims.values():
            check("storage" in t["spec"]["resources"]["requests"], "the data claim requests no storage")
        ports = {p["name"]: p["containerPort"] for p in c["ports"]}
        check(ports.get(svc["spec"]["ports"][0]["targetPort"]) == PORT, "the Service does not reach port 8640")
        check(env.get("FURNACE_BIND", {}).get("value") == f"0.0.0.0:{PORT}", "the coordinator does not bind 0.0.0.0:8640")
        check(c["readinessProbe"]["httpGet"]["path"] == "/readyz", "readiness is not /readyz")
        check(c["livenessProbe"]["httpGet"]["path"] == "/healthz", "liveness is not /healthz")
        check_args(furnace, "coordinator container", c["args"], env)
        # Workers: the coordinator through its Service, a drain, a grace period for it.
        wpod = dep["spec"]["template"]["spec"]
        (w,) = wpod["containers"]
        wenv = env_of(w)
        svc_url = f"http://{svc['metadata']['name']}:{svc['spec']['ports'][0]['port']}"
        check(wenv.get("FURNACE_COORDINATOR", {}).get("value") == svc_url, f"workers do not reach {svc_url}")
        check("preStop" in w.get("lifecycle", {}), "workers have no preStop drain")
        check(wpod.get("terminationGracePeriodSeconds", 30) >= 600, "workers' grace period is under 10 minutes")
        check("livenessProbe" not in w, "a worker waiting out a coordinator outage must not be restarted")
        check_args(furnace, "worker container", w["args"], wenv)
        check_args(furnace, "worker readiness probe", w["readinessProbe"]["exec"]["command"][1:])
        # Both run as the image's non-root user, with the token from the Secret.
        for what, p, cont in [("coordinator", pod, c), ("worker", wpod, w)]:
            sc = p.get("securityContext", {})
            check(sc.get("runAsNonRoot") is True and sc.get("runAsUser") == UID, f"{what} does not run as uid {UID}")
            ref = env_of(cont).get("FURNACE_TOKEN", {}).get("valueFrom", {}).get("secretKeyRef", {})
            check(ref == {"name": "furnace-token", "key": "token"}, f"{what}'s token is not from Secret furnace-token")
        hpas = by_kind(objs, "HorizontalPodAutoscaler")
        scaled = by_kind(objs, "ScaledObject")
        if name == "keda":
            check(not hpas, "the KEDA overlay must not also have an HPA (they would fight)")
            so = scaled.get("furnace-worker")
            if check(so, "no ScaledObject"):
                s = so["spec"]
                check(s["scaleTargetRef"]["name"] == dep["metadata"]["name"], "ScaledObject scales something else")
                check(s.get("minReplicaCount", 1) == 0, "KEDA should scale workers to zero")
                (t,) = s["triggers"]
                m = t["metadata"]
                check(t["type"] == "metrics-api", "the trigger is not metrics-api")
                check(m["url"] == svc_url + "/v1/stats", "the trigger does not read /v1/stats")
                check(m["valueLocation"] == "pending_chunks", "the trigger does not read pending_chunks")
                check(float(m["targetValue"]) > 0, "targetValue must be positive")
                check(m.get("authMode") == "bearer", "the trigger sends no bearer token")
                ta = by_kind(objs, "TriggerAuthentication").get(t["authenticationRef"]["name"])
                if check(ta, "the trigger's TriggerAuthentication is missing"):
                    (ref,) = ta["spec"]["secretTargetRef"]
                    check(ref == {"parameter": "token", "name": "furnace-token", "key": "token"},
                          "the TriggerAuthentication does not read Secret furnace-token")
        else:
            check(not scaled, "the HPA overlay must not need KEDA")
            hpa = hpas.get("furnace-worker")
            if check(hpa, "no HPA"):
                ref = hpa["spec"]["scaleTargetRef"]
                check((ref["kind"], ref["name"]) == ("Deployment", dep["metadata"]["name"]), "the HPA scales something else")
    # The batch alternative: an Indexed Job of workers that exit when the work is done.
    (job,) = yaml.safe_load_all(open(os.path.join(ROOT, "deploy/kubernetes/indexed-job.yaml")))
    try:
        kubernetes_validate.validate(job, K8S_VERSION, strict=True)
    except kubernetes_validate.ValidationError as e:
        check(False, f"indexed-job.yaml: {e.message} at {list(e.path)}")
    spec = job["spec"]
    check(spec.get("completionMode") == "Indexed", "indexed-job.yaml is not an Indexed Job")
    (w,) = spec["template"]["spec"]["containers"]
    check("--exit-when-idle" in w["args"], "Job workers must exit when the work is done")
    check_args(furnace, "indexed-job.yaml", w["args"], env_of(w))
    ref = env_of(w).get("FURNACE_TOKEN", {}).get("valueFrom", {}).get("secretKeyRef", {})
    check(ref == {"name": "furnace-token", "key": "token"}, "indexed-job.yaml: the token is not from the Secret")
    overlays["indexed-job"] = [job]
    return overlays


def dockerfile_stages():
    """Stage name -> its instructions (with continuation lines joined)."""
    text = open(os.path.join(ROOT, "deploy/docker/Dockerfile")).read().replace("\\\n", " ")
    stages, cur = {}, None
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        op, _, rest = line.partition(" ")
        if op.upper() == "FROM":
            m = re.match(r"(\S+)(?:\s+AS\s+(\S+))?", rest, re.I)
            cur = m.group(2)
            stages[cur] = {"from": m.group(1), "ops": []}
        elif cur is not None:  # (a global ARG before the first FROM belongs to no stage)
            stages[cur]["ops"].append((op.upper(), rest.strip()))
    return stages


def resolved(stages, name, op):
    """The last `op` of a stage, following its FROM chain."""
    while name in stages:
        found = [r for o, r in stages[name]["ops"] if o == op]
        if found:
            return found[-1]
        name = stages[name]["from"]
    return None


def stage_env(stages, name):
    """The FURNACE_* variables a stage's own ENV sets."""
    return dict(re.findall(r"(FURNACE_[A-Z_]+)=(\S+)", " ".join(r for o, r in stages[name]["ops"] if o == "ENV")))


def check_docker(furnace):
    stages = dockerfile_stages()
    for target in ["coordinator", "worker"]:
        if not check(target in stages, f"Dockerfile has no '{target}' target"):
            continue
        user = resolved(stages, target, "USER")
        check(user is not None and user.split(":")[0] == str(UID), f"{target}: USER is not {UID}")
        hc = resolved(stages, target, "HEALTHCHECK")
        if check(hc, f"{target}: no HEALTHCHECK"):
            cmd = json.loads(hc[hc.index("CMD") + 3:])
            check(cmd[0] == "furnace", f"{target}: the health check does not run furnace")
            check_args(furnace, f"{target} HEALTHCHECK", cmd[1:])
        env = stage_env(stages, target)
        check_args(furnace, f"{target} CMD", json.loads(resolved(stages, target, "CMD")), env)
    check(json.loads(resolved(stages, "coordinator", "ENTRYPOINT")) == ["furnace"], "ENTRYPOINT is not furnace")
    return stages


def metric_names(text):
    names = set()
    for line in text.splitlines():
        if line and not line.startswith("#"):
            names.add(re.match(r"[a-zA-Z_:][a-zA-Z0-9_:]*", line).group(0))
    return names


def check_compose(furnace, stages, metrics_text):
    base = os.path.join(ROOT, "deploy/compose")
    c = yaml.safe_load(open(os.path.join(base, "compose.yaml")))
    s = c["services"]
    for name in ["coordinator", "worker"]:
        if not check(name in s, f"compose: no service {name}"):
            return
        b = s[name]["build"]
        check(b["target"] in stages, f"compose: {name} builds target {b['target']}, not in the Dockerfile")
        check(os.path.exists(os.path.join(base, b["context"], b["dockerfile"])), f"compose: {name}'s Dockerfile is missing")
        check("FURNACE_TOKEN" in s[name]["environment"], f"compose: {name} has no token")
    data_dir = stage_env(stages, "coordinator")["FURNACE_DATA_DIR"]
    vols = [v.split(":") for v in s["coordinator"].get("volumes", [])]
    check(any(v[0] in c.get("volumes", {}) and v[1] == data_dir for v in vols), "compose: the data dir is not on a named volume")
    w = s["worker"]
    check("container_name" not in w and "ports" not in w, "compose: workers cannot be scaled with a fixed name or port")
    check(w["environment"]["FURNACE_COORDINATOR"] == f"http://coordinator:{PORT}", "compose: workers do not reach the coordinator")
    check(w.get("depends_on", {}).get("coordinator", {}).get("condition") == "service_healthy", "compose: workers start before the coordinator is healthy")
    grace = w.get("stop_grace_period", "10s")
    check(grace.endswith("m") or grace.endswith("h"), "compose: workers need a stop grace period of minutes")
    for name in ["prometheus", "grafana"]:
        check(s.get(name, {}).get("profiles") == ["monitoring"], f"compose: {name} is not in the monitoring profile")
    prom = yaml.safe_load(open(os.path.join(base, "prometheus.yml")))
    (job,) = prom["scrape_configs"]
    check(job.get("metrics_path", "/metrics") == "/metrics", "prometheus does not scrape /metrics")
    check(job["static_configs"][0]["targets"] == [f"coordinator:{PORT}"], "prometheus does not scrape the coordinator")
    # Grafana: the provisioned folders are mounted, the dashboard uses the provisioned source.
    mounts = dict(v.split(":")[:2] for v in s["grafana"]["volumes"])
    prov = mounts.get("./grafana/provisioning")
    check(prov == "/etc/grafana/provisioning", "grafana: provisioning is not mounted")
    dsrc = yaml.safe_load(open(os.path.join(base, "grafana/provisioning/datasources/prometheus.yaml")))["datasources"][0]
    check(dsrc["url"] == "http://prometheus:9090", "grafana: the datasource is not the prometheus service")
    prov_d = yaml.safe_load(open(os.path.join(base, "grafana/provisioning/dashboards/furnace.yaml")))["providers"][0]
    check(mounts.get("./grafana/dashboards") == prov_d["options"]["path"], "grafana: the dashboards folder is not where the provider reads")
    dash = json.load(open(os.path.join(base, "grafana/dashboards/furnace.json")))
    exported = metric_names(metrics_text)
    used = set()
    for p in dash["panels"]:
        check(p["datasource"]["uid"] == dsrc["uid"], f"grafana panel {p['title']}: not the provisioned datasource")
        for t in p["targets"]:
            used |= set(re.findall(r"\bfurnace_[a-z_]+", t["expr"]))
    for m in sorted(used - exported):
        check(False, f"grafana queries {m}, which /metrics does not export")
    check(len(used) >= 10, "the dashboard shows too little")
    return used


def check_compose_host(stages):
    """compose.host.yaml: compose.yaml's coordinator and workers on the host's network, the
    coordinator on loopback at the port its HEALTHCHECK probes, the workers pointed there."""
    base = os.path.join(ROOT, "deploy/compose")
    c = yaml.safe_load(open(os.path.join(base, "compose.host.yaml")))
    main_file = yaml.safe_load(open(os.path.join(base, "compose.yaml")))
    s = c["services"]
    for name in ["coordinator", "worker"]:
        if not check(name in s, f"compose.host: no service {name}"):
            return
        check(s[name].get("network_mode") == "host", f"compose.host: {name} is not on the host's network")
        check(s[name]["build"]["target"] == main_file["services"][name]["build"]["target"], f"compose.host: {name} builds another target")
        check(s[name]["image"] == main_file["services"][name]["image"], f"compose.host: {name} is another image")
        check("ports" not in s[name], f"compose.host: {name} publishes ports on the host's network")
        check("FURNACE_TOKEN" in s[name]["environment"], f"compose.host: {name} has no token")
    bind = s["coordinator"]["environment"]["FURNACE_BIND"]
    check(bind == f"127.0.0.1:{PORT}", f"compose.host: the coordinator binds {bind}, not loopback at {PORT}")
    hc = resolved(stages, "coordinator", "HEALTHCHECK")
    check(f"127.0.0.1:{PORT}/" in hc, "compose.host: the coordinator's HEALTHCHECK probes another address")
    check(s["worker"]["environment"]["FURNACE_COORDINATOR"] == f"http://{bind}", "compose.host: workers do not reach the coordinator")
    check(s["worker"].get("depends_on", {}).get("coordinator", {}).get("condition") == "service_healthy", "compose.host: workers start before the coordinator is healthy")
    check(s["worker"].get("stop_grace_period", "10s")[-1] in "mh", "compose.host: workers need a stop grace period of minutes")
    prom = yaml.safe_load(open(os.path.join(base, "prometheus.host.yml")))
    check(prom["scrape_configs"][0]["static_configs"][0]["targets"] == [bind], "compose.host: prometheus does not scrape the coordinator")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--furnace", required=True)
    ap.add_argument("--metrics", required=True, help="a /metrics scrape of a coordinator that ran a job")
    a = ap.parse_args()
    overlays = check_kubernetes(a.furnace)
    stages = check_docker(a.furnace)
    used = check_compose(a.furnace, stages, open(a.metrics).read())
    check_compose_host(stages)
    if failures:
        print("\n".join(failures))
        sys.exit(1)
    counts = {k: len(v) for k, v in overlays.items()}
    print(f"ok: objects per overlay {counts} valid for Kubernetes {K8S_VERSION}; Dockerfile targets "
          f"{sorted(s for s in stages if s)}; {len(used)} metrics on the Grafana dashboard")


if __name__ == "__main__":
    main()
