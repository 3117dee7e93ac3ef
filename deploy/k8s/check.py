#!/usr/bin/env python3
"""Checks rendered socialflow manifests against the Kubernetes schemas and against the code.

Usage: check.py --bin BIN --repo REPO [--k8s-version 1.30] [--extra FILE]... NAME=RENDERED[:EXTRA]...
Each NAME=RENDERED is one rendered overlay, checked together with its own :EXTRA files (e.g. an
example that only fits it) and with every --extra file (monitoring). Prints one line per check; exits 1 on any failure.

Schema: every object against kubernetes-validate's strict schemas for the pinned version;
monitoring.coreos.com/v1 objects (no schema there) get a minimal shape check.
Consistency with the code:
  - container args: the subcommand exists and every --flag is in `BIN <subcommand> --help`;
    every SOCIALFLOW_* env var set is in that help's [env: ...] list; files passed by flag are
    under a volume mount and exist in their ConfigMap;
  - the learner's learner.toml (from its ConfigMap): keys are LearnerConfig fields; gRPC/admin
    ports agree with container ports, probes, Services, NetworkPolicies, scrape annotations;
    data_dir is the StatefulSet's volume; terminationGracePeriodSeconds covers shutdown;
  - workers: --admin-addr agrees with ports and probes; --learner names the learner Service,
    its port and the right scheme (https when the learner serves TLS);
  - probe paths are routes of crates/service/src/admin.rs;
  - images are what deploy/build-images.sh builds;
  - PrometheusRule expressions use only metric names the services export;
  - the sample job's keys are JobConfig fields and its device matches the learner's GPU request;
  - security context: non-root numeric user, read-only root filesystem, requests and limits.
"""

import argparse
import functools
import os
import re
import subprocess
import sys
import tomllib

import yaml

FAILS = []
SECTION = [""]


def check(ok, what, detail=""):
    if ok:
        print(f"  ok    {what}")
    else:
        print(f"  FAIL  {what}{': ' + detail if detail else ''}")
        FAILS.append(f"[{SECTION[0]}] {what}" if SECTION[0] else what)
    return ok


def read(repo, rel):
    with open(os.path.join(repo, rel)) as f:
        return f.read()


# ---------------------------------------------------------------- facts from the code


@functools.lru_cache(maxsize=None)
def help_of(bin_path, sub):
    try:
        r = subprocess.run([bin_path, sub, "--help"], capture_output=True, text=True, timeout=60)
    except OSError:
        return None
    if r.returncode != 0:
        return None
    text = r.stdout + r.stderr
    flags = set(re.findall(r"(?<![\w-])(--[a-z0-9][a-z0-9-]*)", text))
    envs = set(re.findall(r"\[env:\s*([A-Z0-9_]+)=", text))
    return flags, envs


def struct_fields(src, name):
    m = re.search(r"pub struct " + name + r"\s*\{(.*?)\n\}", src, re.S)
    return set(re.findall(r"^\s*pub (\w+):", m.group(1), re.M)) if m else set()


def enum_variants_kebab(src, name):
    m = re.search(r"pub enum " + name + r"\s*\{(.*?)\n\}", src, re.S)
    out = set()
    for v in re.findall(r"^\s*([A-Z]\w*),", m.group(1), re.M) if m else []:
        out.add(re.sub(r"(?<!^)([A-Z])", r"-\1", v).lower())
    return out


def exported_metrics(repo):
    """Names on /metrics: prometheus-client's text encoder appends `_total` to counters and
    `_bucket`/`_sum`/`_count` to histograms; no registry prefix is used (checked)."""
    files = [os.path.join("crates/service/src/metrics.rs")]
    for svc in sorted(os.listdir(os.path.join(repo, "services"))):
        d = os.path.join("services", svc, "src")
        if not os.path.isdir(os.path.join(repo, d)):
            continue
        files += [os.path.join(d, f) for f in sorted(os.listdir(os.path.join(repo, d))) if f.endswith(".rs")]
    srcs = {f: read(repo, f) for f in files}
    all_src = "\n".join(srcs.values())
    # Calls may span lines with a trailing comma (rustfmt at width 100).
    components = set(re.findall(r'CommonMetrics::register\(\s*\w+\s*,\s*"(\w+)"\s*,?\s*\)', all_src))
    prefixed = "Registry::with_prefix" in all_src
    names = {}
    reg = re.compile(r'\.register\(\s*(?:"([^"]+)"|format!\("([^"]+)"\))\s*,\s*"[^"]*"\s*,\s*m\.(\w+)\.clone\(\)\s*,?\s*\)')
    for f, src in srcs.items():
        fields = dict(re.findall(r"^\s*pub (\w+):\s*([^\n]+?),\s*$", src, re.M))
        for lit, fmt, field in reg.findall(src):
            typ = fields.get(field, "")
            kind = "histogram" if "Histogram" in typ else "counter" if "Counter" in typ else "gauge"
            bases = [lit] if lit else [fmt.replace("{component}", c) for c in sorted(components)]
            for b in bases:
                if kind == "counter":
                    names[b + "_total"] = f
                elif kind == "histogram":
                    for s in ("_bucket", "_sum", "_count"):
                        names[b + s] = f
                else:
                    names[b] = f
    return names, prefixed, components


def admin_routes(repo):
    return set(re.findall(r'\.route\("(/[^"]*)"', read(repo, "crates/service/src/admin.rs")))


def built_image(repo):
    m = re.search(r"docker build\b[^\n]*?-t (\S+) -f Dockerfile\b", read(repo, "deploy/build-images.sh"))
    return m.group(1) if m else None


# ---------------------------------------------------------------- manifest helpers


def split_image(ref):
    name, _, _digest = ref.partition("@")
    slash, colon = name.rfind("/"), name.rfind(":")
    tag = ""
    if colon > slash:
        name, tag = name[:colon], name[colon + 1:]
    return name, tag


def selects(selector, labels):
    if selector is None:
        return False
    for k, v in (selector.get("matchLabels") or {}).items():
        if labels.get(k) != v:
            return False
    for e in selector.get("matchExpressions") or []:
        k, op, vals = e["key"], e["operator"], e.get("values", [])
        if op == "In" and labels.get(k) not in vals or op == "NotIn" and labels.get(k) in vals:
            return False
        if op == "Exists" and k not in labels or op == "DoesNotExist" and k in labels:
            return False
    return True


def workloads(objs):
    for o in objs:
        spec = o.get("spec", {})
        if o["kind"] in ("Deployment", "StatefulSet", "DaemonSet", "Job", "ReplicaSet"):
            yield o, spec["template"]["metadata"].get("labels", {}), spec["template"]["spec"], spec["template"]["metadata"].get("annotations", {})
        elif o["kind"] == "Pod":
            yield o, o["metadata"].get("labels", {}), spec, o["metadata"].get("annotations", {})


def oname(o):
    m = o.get("metadata", {})
    return m.get("name") or m.get("generateName", "") + "*"


def port_of(addr):
    return int(str(addr).rsplit(":", 1)[1])


def flag_value(args, flag):
    for i, a in enumerate(args):
        if a == flag and i + 1 < len(args):
            return args[i + 1]
        if a.startswith(flag + "="):
            return a.split("=", 1)[1]
    return None


def resolve_port(port, container):
    if isinstance(port, int):
        return port
    for p in container.get("ports", []):
        if p.get("name") == port:
            return p["containerPort"]
    return None


def file_source(path, container, pod, objs, ns):
    """(kind, name, key, data or None) of the volume file at `path`, or None if no mount holds it."""
    for m in container.get("volumeMounts", []):
        mp = m["mountPath"].rstrip("/")
        if not path.startswith(mp + "/"):
            continue
        rel = path[len(mp) + 1:]
        vol = next((v for v in pod.get("volumes", []) if v["name"] == m["name"]), None)
        if vol is None:
            return ("missing volume", m["name"], rel, None)
        src = vol.get("configMap") or vol.get("secret")
        if src is None:
            return ("other", m["name"], rel, None)
        kind = "ConfigMap" if "configMap" in vol else "Secret"
        name = src.get("name") or src.get("secretName")
        key = rel
        if src.get("items"):
            key = next((i["key"] for i in src["items"] if i["path"] == rel), None)
        cm = next((o for o in objs if o["kind"] == kind and o["metadata"]["name"] == name and o["metadata"].get("namespace") == ns), None)
        data = None if cm is None else (cm.get("data") or {})
        return (kind, name, key, data)
    return None


# ---------------------------------------------------------------- schema


def schema_checks(label, objs, version):
    import kubernetes_validate

    SECTION[0] = label
    print(f"[{label}] schemas (Kubernetes {version}, strict)")
    for o in objs:
        what = f"{o.get('kind')}/{oname(o)}"
        if o.get("apiVersion", "").startswith("monitoring.coreos.com/"):
            shape_ok = isinstance(o.get("metadata", {}).get("name"), str) and isinstance(o.get("spec"), dict)
            kind = o["kind"]
            if kind == "ServiceMonitor":
                shape_ok &= isinstance(o["spec"].get("selector"), dict) and all("port" in e for e in o["spec"].get("endpoints", [])) and bool(o["spec"].get("endpoints"))
            elif kind == "PodMonitor":
                shape_ok &= isinstance(o["spec"].get("selector"), dict) and all("port" in e for e in o["spec"].get("podMetricsEndpoints", [])) and bool(o["spec"].get("podMetricsEndpoints"))
            elif kind == "PrometheusRule":
                rules = [r for g in o["spec"].get("groups", []) for r in g.get("rules", [])]
                shape_ok &= bool(rules) and all(("alert" in r) != ("record" in r) and isinstance(r.get("expr"), str) for r in rules)
            else:
                shape_ok = False
            check(shape_ok, f"{what}: {o['apiVersion']} shape (CRD: no upstream schema, minimal check)")
            continue
        try:
            kubernetes_validate.validate(o, version, strict=True)
            check(True, f"{what} validates")
        except kubernetes_validate.ValidationError as e:
            check(False, f"{what} validates", f"{'.'.join(str(p) for p in e.path)}: {e.message}")
        except kubernetes_validate.SchemaNotFoundError as e:
            check(False, f"{what} has a schema", e.message)


# ---------------------------------------------------------------- consistency


def consistency_checks(label, objs, a, facts):
    SECTION[0] = label
    print(f"[{label}] consistency with the code")
    routes, image, lcfg_fields, job_fields, devices, metrics = facts
    ns_of = lambda o: o["metadata"].get("namespace")
    sf = []  # (obj, pod labels, pod spec, annotations, container, subcommand)
    for o, labels, pod, ann in workloads(objs):
        for c in pod.get("containers", []):
            if split_image(c.get("image", ""))[0].rsplit("/", 1)[-1] == "socialflow":
                sf.append((o, labels, pod, ann, c, (c.get("args") or [""])[0]))

    # images
    for o, _, _, _, c, _ in sf:
        name, tag = split_image(c["image"])
        if "/" in name:
            check(name.rsplit("/", 1)[-1] == split_image(image)[0], f"{o['kind']}/{oname(o)}: image {c['image']} is {image} pushed to a registry")
        else:
            check(c["image"] == image, f"{o['kind']}/{oname(o)}: image {c['image']} is what deploy/build-images.sh builds ({image})")
        check(c.get("command") in (None, ["/app/socialflow"]), f"{c['name']}: keeps the image's entrypoint /app/socialflow")

    # args and env against --help
    for o, _, pod, _, c, sub in sf:
        h = help_of(a.bin, sub)
        if not check(h is not None, f"{c['name']}: `socialflow {sub}` is a subcommand"):
            continue
        flags, envs = h
        used = [x.split("=", 1)[0] for x in c.get("args", []) if x.startswith("--")]
        bad = [f for f in used if f not in flags]
        check(not bad, f"{c['name']}: flags {' '.join(used)} are in `socialflow {sub} --help`", f"unknown {bad}")
        set_env = [e["name"] for e in c.get("env", []) if e["name"].startswith("SOCIALFLOW_")]
        bad = [e for e in set_env if e not in envs]
        check(not bad, f"{c['name']}: env {' '.join(set_env) or '(no SOCIALFLOW_* vars)'} in the help's env list", f"unknown {bad}")
        args = c.get("args", [])
        files = [(f, flag_value(args, f)) for f in used if f.endswith("-file") or f == "--config"]
        if sub == "submit" and len(args) > 1 and not args[1].startswith("-"):
            files.append(("<config>", args[1]))
        for f, path in files:
            src = file_source(path, c, pod, objs, ns_of(o))
            if not check(src is not None and src[0] in ("ConfigMap", "Secret"), f"{c['name']}: {f} {path} is on a ConfigMap/Secret volume"):
                continue
            kind, name, key, data = src
            if kind == "ConfigMap":
                check(data is not None and key in data, f"{c['name']}: {f} {path} is key {key} of ConfigMap {name}")
            else:
                check(key is not None, f"{c['name']}: {f} {path} is key {key} of Secret {name} (created outside the manifests)")

    # security context and resources
    for o, _, pod, _, c, _ in sf:
        psc, csc = pod.get("securityContext", {}), c.get("securityContext", {})
        eff = {**psc, **csc}
        check(eff.get("runAsNonRoot") is True and isinstance(eff.get("runAsUser"), int) and eff["runAsUser"] > 0, f"{c['name']}: runAsNonRoot with a numeric non-root runAsUser")
        check(csc.get("readOnlyRootFilesystem") is True and csc.get("allowPrivilegeEscalation") is False, f"{c['name']}: read-only root filesystem, no privilege escalation")
        r = c.get("resources", {})
        check(all(k in r.get("requests", {}) for k in ("cpu", "memory")) and "memory" in r.get("limits", {}), f"{c['name']}: cpu/memory requests and a memory limit")

    # probe paths
    for o, _, _, _, c, _ in sf:
        for pn in ("startupProbe", "readinessProbe", "livenessProbe"):
            p = c.get(pn) or {}
            if "httpGet" in p:
                check(p["httpGet"].get("path") in routes, f"{c['name']}: {pn} path {p['httpGet'].get('path')} is an admin route {sorted(routes)}")

    learners = [x for x in sf if x[5] == "learner"]
    workers = [x for x in sf if x[5] == "worker"]
    clients = [x for x in sf if x[5] in ("worker", "submit", "status", "watch", "cancel")]
    if not check(len(learners) == 1, "exactly one learner container"):
        return
    lo, llabels, lpod, lann, lc, _ = learners[0]
    largs = lc.get("args", [])
    cfg_path = flag_value(largs, "--config")
    src = file_source(cfg_path, lc, lpod, objs, ns_of(lo)) if cfg_path else None
    if not check(src is not None and src[3] is not None and src[2] in src[3], f"learner config {cfg_path} comes from a rendered ConfigMap"):
        return
    try:
        cfg = tomllib.loads(src[3][src[2]])
    except tomllib.TOMLDecodeError as e:
        check(False, "learner.toml parses", str(e))
        return
    bad = sorted(set(cfg) - lcfg_fields)
    check(not bad, f"learner.toml keys {sorted(cfg)} are LearnerConfig fields", f"unknown {bad}")
    grpc = port_of(flag_value(largs, "--grpc-addr") or cfg.get("grpc_addr", "0.0.0.0:50051"))
    admin = port_of(flag_value(largs, "--admin-addr") or cfg.get("admin_addr", "0.0.0.0:9090"))
    print(f"        learner ports from learner.toml/flags: grpc {grpc}, admin {admin}")
    check(resolve_port("grpc", lc) == grpc, f"learner container port `grpc` = {grpc}", f"got {resolve_port('grpc', lc)}")
    check(resolve_port("admin", lc) == admin, f"learner container port `admin` = {admin}", f"got {resolve_port('admin', lc)}")
    tls = bool(flag_value(largs, "--tls-cert-file") or cfg.get("tls_cert_file"))
    plaintext_ok = "--allow-plaintext-token" in largs or cfg.get("allow_plaintext_token") is True
    if "--allow-plaintext-token" in (help_of(a.bin, "learner") or ((), ()))[0] or "allow_plaintext_token" in lcfg_fields:
        # Workers' tokens come from pod IPs, not loopback.
        check(tls or plaintext_ok, "plaintext learner accepts tokens from the pod network (--allow-plaintext-token)")
        check(not (tls and plaintext_ok), "TLS learner does not also allow plaintext tokens")
    for pn in ("startupProbe", "readinessProbe", "livenessProbe"):
        p = lc.get(pn)
        if p is None:
            check(pn == "startupProbe", f"learner has a {pn}")
            continue
        if "grpc" in p:
            check(p["grpc"].get("port") == grpc and not tls, f"learner {pn}: gRPC health on port {grpc} (plaintext)", f"port {p['grpc'].get('port')}, tls {tls}")
        elif "httpGet" in p:
            check(resolve_port(p["httpGet"]["port"], lc) == admin, f"learner {pn}: HTTP on the admin port {admin}")
        else:
            check(False, f"learner {pn} is gRPC or HTTP")
    check(str(lann.get("prometheus.io/port")) == str(admin), f"learner scrape annotation port = {admin}")
    data_dir = flag_value(largs, "--data-dir") or cfg.get("data_dir")
    vct = [t["metadata"]["name"] for t in lo["spec"].get("volumeClaimTemplates", [])]
    mounted = [m["name"] for m in lc.get("volumeMounts", []) if m["mountPath"].rstrip("/") == str(data_dir).rstrip("/")]
    check(lo["kind"] == "StatefulSet" and lo["spec"].get("replicas") == 1, "learner is a StatefulSet of 1")
    check(bool(mounted) and mounted[0] in vct, f"data_dir {data_dir} is the StatefulSet's volumeClaimTemplate", f"mounted {mounted}, templates {vct}")
    for k in ("scenarios_dir", "cases_dir"):
        v = cfg.get(k, "")
        check(v.startswith("/app/configs/") and os.path.isdir(os.path.join(a.repo, "configs", v[len("/app/configs/"):])), f"learner.toml {k} {v} is in the image (configs/ copied to /app/configs)")
    grace = int(cfg.get("shutdown_grace_s", 120))
    need = 2 * grace + 5 + 10
    tgp = lpod.get("terminationGracePeriodSeconds", 30)
    check(tgp >= need, f"terminationGracePeriodSeconds {tgp} >= 2 x shutdown_grace_s + 5 s server stop + 10 s margin = {need}")

    # Services of the learner
    lsvcs = [o for o in objs if o["kind"] == "Service" and selects({"matchLabels": o["spec"].get("selector", {})}, llabels)]
    check(any(o["spec"].get("clusterIP") == "None" and o["metadata"]["name"] == lo["spec"].get("serviceName") for o in lsvcs), "the StatefulSet's serviceName is a headless Service of the learner")
    for s in lsvcs:
        for p in s["spec"]["ports"]:
            tp = resolve_port(p.get("targetPort", p["port"]), lc)
            check(tp in (grpc, admin), f"Service {s['metadata']['name']} port {p.get('name')} targets a learner port", f"targets {tp}")
    grpc_svc = {s["metadata"]["name"]: p["port"] for s in lsvcs if s["spec"].get("clusterIP") != "None" for p in s["spec"]["ports"] if resolve_port(p.get("targetPort", p["port"]), lc) == grpc}
    check(bool(grpc_svc), f"a ClusterIP Service exposes the learner's gRPC port: {grpc_svc}")

    # workers and clients
    for o, wlabels, wpod, wann, c, sub in clients:
        args = c.get("args", [])
        url = flag_value(args, "--learner") or "http://127.0.0.1:50051"
        m = re.match(r"^(https?)://([^:/]+):(\d+)/?$", url)
        if not check(m is not None, f"{c['name']}: --learner {url} is scheme://host:port"):
            continue
        scheme, host, port = m.group(1), m.group(2), int(m.group(3))
        labels = host.split(".")
        ns_ok = len(labels) == 1 or labels[1] == ns_of(lo)
        check(labels[0] in grpc_svc and grpc_svc[labels[0]] == port and ns_ok, f"{c['name']}: --learner {url} is the learner's gRPC Service", f"services {grpc_svc}, namespace {ns_of(lo)}")
        check((scheme == "https") == tls, f"{c['name']}: scheme {scheme} matches the learner's TLS ({'on' if tls else 'off'})")
        if tls:
            check(flag_value(args, "--tls-ca-file") is not None, f"{c['name']}: --tls-ca-file given for https")
    for o, wlabels, wpod, wann, c, sub in workers:
        addr = flag_value(c.get("args", []), "--admin-addr")
        if not check(addr is not None, f"{c['name']}: --admin-addr set (metrics and probes)"):
            continue
        wadmin = port_of(addr)
        check(addr.startswith("0.0.0.0:"), f"{c['name']}: admin listens on all interfaces ({addr})")
        check(resolve_port("admin", c) == wadmin, f"{c['name']}: container port `admin` = --admin-addr port {wadmin}")
        for pn in ("readinessProbe", "livenessProbe"):
            p = c.get(pn) or {}
            check("httpGet" in p and resolve_port(p["httpGet"]["port"], c) == wadmin, f"{c['name']}: {pn} is HTTP on port {wadmin}")
        check(str(wann.get("prometheus.io/port")) == str(wadmin), f"{c['name']}: scrape annotation port = {wadmin}")

    # NetworkPolicies
    pols = [o for o in objs if o["kind"] == "NetworkPolicy"]
    lpols = [p for p in pols if selects(p["spec"]["podSelector"], llabels)]
    if check(bool(lpols), "a NetworkPolicy guards the learner"):
        rules = [r for p in lpols for r in p["spec"].get("ingress", [])]
        ports = {pp.get("port") for r in rules for pp in r.get("ports", [])}
        check(ports == {grpc, admin}, f"learner NetworkPolicy ports {sorted(ports, key=str)} = gRPC {grpc} + admin {admin}")
        grpc_rules = [r for r in rules if any(pp.get("port") == grpc for pp in r.get("ports", []))]
        for o, clabels, _, _, c, sub in clients:
            check(any(any("podSelector" in f and "namespaceSelector" not in f and selects(f["podSelector"], clabels) for f in r.get("from", [])) for r in grpc_rules), f"{c['name']}: NetworkPolicy admits it to the learner's gRPC port")
        for r in grpc_rules:
            for f in r.get("from", []):
                ml = (f.get("podSelector") or {}).get("matchLabels", {})
                check("namespaceSelector" not in f and (ml.get("app.kubernetes.io/component") == "worker" or ml.get("socialflow.io/client") == "true"), f"gRPC ingress source {ml} is workers or socialflow.io/client pods only")
        check(all(all("namespaceSelector" in f and "podSelector" not in f for f in r.get("from", [])) for r in rules if r not in grpc_rules), "admin port is open to the monitoring namespace only")
    for o, wlabels, _, _, c, _ in workers:
        wpols = [p for p in pols if selects(p["spec"]["podSelector"], wlabels)]
        ports = {pp.get("port") for p in wpols for r in p["spec"].get("ingress", []) for pp in r.get("ports", [])}
        check(ports == {port_of(flag_value(c.get("args", []), "--admin-addr") or "0:0")}, f"worker NetworkPolicy admits only the admin port {sorted(ports)}")

    # sample job
    jobs = [o for o in objs if o["kind"] == "ConfigMap" and "job.toml" in (o.get("data") or {})]
    if check(bool(jobs), "a sample job ConfigMap (key job.toml)"):
        try:
            job = tomllib.loads(jobs[0]["data"]["job.toml"])
        except tomllib.TOMLDecodeError as e:
            check(False, "sample job.toml parses", str(e))
            job = {}

        def keys(d):
            for k, v in d.items():
                yield k
                if isinstance(v, dict):
                    yield from keys(v)

        bad = sorted(set(keys(job)) - job_fields)
        check(not bad, "sample job keys are JobConfig fields (crates/job/src/config/)", f"unknown {bad}")
        device = job.get("sac", {}).get("device", "cpu")
        gpu = "nvidia.com/gpu" in (lc.get("resources", {}).get("limits") or {})
        check(device in devices, f"sample job sac.device {device!r} is one of {sorted(devices)}")
        check((device == "cuda") == gpu, f"sample job device {device!r} matches the learner's GPU request ({'nvidia.com/gpu' if gpu else 'none'})")

    # monitoring
    for o in objs:
        if o["kind"] == "ServiceMonitor":
            svcs = [s for s in objs if s["kind"] == "Service" and selects(o["spec"]["selector"], s["metadata"].get("labels", {}))]
            check(len(svcs) == 1, f"ServiceMonitor {o['metadata']['name']} selects one Service", f"{[s['metadata']['name'] for s in svcs]}")
            for e in o["spec"]["endpoints"]:
                p = next((p for s in svcs for p in s["spec"]["ports"] if p.get("name") == e["port"]), None)
                check(p is not None and resolve_port(p.get("targetPort", p["port"]), lc) == admin, f"ServiceMonitor port {e['port']} is the learner's admin port")
        if o["kind"] == "PodMonitor":
            sel = [c for _, labels, _, _, c, _ in sf if selects(o["spec"]["selector"], labels)]
            check(bool(sel), f"PodMonitor {o['metadata']['name']} selects socialflow pods ({[c['name'] for c in sel]})")
            for e in o["spec"]["podMetricsEndpoints"]:
                check(all(resolve_port(e["port"], c) is not None for c in sel), f"PodMonitor port {e['port']} is a named port of those containers")
        if o["kind"] == "PrometheusRule":
            exprs = [(r.get("alert") or r.get("record"), r["expr"]) for g in o["spec"]["groups"] for r in g["rules"]]
            for name, expr in exprs:
                used = sorted(set(re.findall(r"\b(socialflow_[a-z0-9_]+)\b", expr)))
                bad = [u for u in used if u not in metrics]
                check(not bad, f"{name}: metrics {', '.join(used) or '(none)'} are exported", f"not exported: {bad}")
                for job_label in re.findall(r'job="([^"]+)"', expr):
                    targets = {m["metadata"]["name"] for m in objs if m["kind"] == "ServiceMonitor"} | {f"{m['metadata'].get('namespace')}/{m['metadata']['name']}" for m in objs if m["kind"] == "PodMonitor"}
                    check(job_label in targets, f"{name}: job=\"{job_label}\" is a scrape job of the monitors {sorted(targets)}")
                for method in re.findall(r'method="([^"]+)"', expr):
                    check(f'"{method}"' in facts_src_service(a.repo), f"{name}: method=\"{method}\" is an RPC label the learner counts (services/learner/src/service.rs)")


@functools.lru_cache(maxsize=None)
def facts_src_service(repo):
    return read(repo, "services/learner/src/service.rs")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", required=True, help="the socialflow binary")
    ap.add_argument("--repo", required=True, help="repository root")
    ap.add_argument("--k8s-version", default="1.30")
    ap.add_argument("--extra", action="append", default=[], help="rendered objects checked with every overlay")
    ap.add_argument("overlays", nargs="+", metavar="NAME=RENDERED[:EXTRA...]")
    a = ap.parse_args()

    def load(p):
        with open(p) as f:
            return [d for d in yaml.safe_load_all(f) if d]

    print("facts from the code")
    routes = admin_routes(a.repo)
    print(f"        admin routes (crates/service/src/admin.rs): {sorted(routes)}")
    check({"/healthz", "/readyz"} <= routes, "admin.rs serves /healthz and /readyz")
    image = built_image(a.repo)
    check(image is not None, f"deploy/build-images.sh builds {image}")
    # LearnerConfig lives in one of the learner's modules (config.rs today): search them all.
    src_dir = os.path.join(a.repo, "services/learner/src")
    lib = "\n".join(read(a.repo, os.path.join("services/learner/src", f)) for f in sorted(os.listdir(src_dir)) if f.endswith(".rs"))
    lcfg = struct_fields(lib, "LearnerConfig")
    check(bool(lcfg), f"LearnerConfig fields: {sorted(lcfg)}")
    # JobConfig is split per section (crates/job/src/config/*.rs): read them all.
    cfg_dir = os.path.join(a.repo, "crates/job/src/config")
    cfg_src = "\n".join(read(a.repo, os.path.join("crates/job/src/config", f)) for f in sorted(os.listdir(cfg_dir)) if f.endswith(".rs"))
    job_fields = set(re.findall(r"^\s*pub (\w+):", cfg_src, re.M))
    devices = enum_variants_kebab(cfg_src, "Device")
    check(bool(job_fields) and "device" in job_fields, f"JobConfig fields ({len(job_fields)}), devices {sorted(devices)}")
    base_job = tomllib.loads(read(a.repo, "deploy/k8s/base/job.toml"))
    gpu_job = tomllib.loads(read(a.repo, "deploy/k8s/overlays/gpu/job.toml"))
    strip = lambda j: {**j, "sac": {k: v for k, v in j.get("sac", {}).items() if k != "device"}}
    check(strip(base_job) == strip(gpu_job), "overlays/gpu/job.toml is base/job.toml but for sac.device")
    metrics, prefixed, comps = exported_metrics(a.repo)
    check(not prefixed, "no Registry::with_prefix (names are registered in full)")
    check(len(metrics) > 10, f"{len(metrics)} exported metric series names (components {sorted(comps)})")
    for sub in ("learner", "worker"):
        h = help_of(a.bin, sub)
        check(h is not None, f"`{a.bin} {sub} --help` runs", "" if h else "non-zero exit")
        if h:
            print(f"        {sub}: {len(h[0])} flags, env {sorted(h[1])}")

    extras = [o for p in a.extra for o in load(p)]
    schema_checks("extras: " + ", ".join(os.path.basename(p) for p in a.extra), extras, a.k8s_version)
    facts = (routes, image, lcfg, job_fields, devices, metrics)
    checked_own = set()
    for spec in a.overlays:
        name, _, paths = spec.partition("=")
        path, *own = paths.split(":")
        objs = load(path)
        schema_checks(name, objs, a.k8s_version)
        for p in own:
            own_objs = load(p)
            if p not in checked_own:
                schema_checks(f"{name} + {os.path.basename(p)}", own_objs, a.k8s_version)
                checked_own.add(p)
            objs += own_objs
        ns = {o["metadata"].get("namespace") for o in objs if o["kind"] != "Namespace"}
        # The extras (examples, monitoring) live in the overlay's namespace.
        consistency_checks(name, objs + [o for o in extras if o["metadata"].get("namespace") in ns], a, facts)

    print()
    if FAILS:
        print(f"{len(FAILS)} check(s) FAILED:")
        for f in FAILS:
            print(f"  - {f}")
        sys.exit(1)
    print("all checks passed")


if __name__ == "__main__":
    main()
