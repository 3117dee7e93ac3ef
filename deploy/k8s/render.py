#!/usr/bin/env python3
"""Renders a kustomization directory to multi-document YAML, without kubectl or kustomize.

Implements only the kustomize features deploy/k8s uses, and refuses any other field rather than
render it wrongly:
  resources (files and directories), components (kind: Component), namespace,
  configMapGenerator / secretGenerator (files, literals; behavior create|replace|merge) with
  generatorOptions.disableNameSuffixHash: true, patches (strategic merge from a file or inline,
  matched by kind and name; lists of containers, env, volumes... merge by their key,
  `$patch: replace|delete` honoured), images (newName, newTag, digest).

Usage: render.py DIR > rendered.yaml
       render.py --same-as KUSTOMIZE_OUTPUT.yaml DIR   (exit 1 if the object sets differ)
`kubectl kustomize DIR` is the reference; this exists so deploy/k8s/validate.sh needs no kubectl,
and validate.sh compares the two where kubectl is installed.
"""

import base64
import copy
import os
import sys

import yaml

KNOWN = {"apiVersion", "kind", "metadata", "namespace", "resources", "components", "patches", "configMapGenerator", "secretGenerator", "generatorOptions", "images"}
CLUSTER_SCOPED = {"Namespace", "ClusterRole", "ClusterRoleBinding", "CustomResourceDefinition", "PersistentVolume", "StorageClass", "PriorityClass"}
# Strategic-merge keys of the list fields we patch (k8s.io/api patchMergeKey); other lists are replaced.
MERGE_KEYS = {"containers": "name", "initContainers": "name", "ephemeralContainers": "name", "env": "name", "volumes": "name", "imagePullSecrets": "name", "volumeMounts": "mountPath", "volumeClaimTemplates": None}


class RenderError(Exception):
    pass


def load_kustomization(d):
    for name in ("kustomization.yaml", "kustomization.yml", "Kustomization"):
        p = os.path.join(d, name)
        if os.path.isfile(p):
            with open(p) as f:
                k = yaml.safe_load(f) or {}
            unknown = set(k) - KNOWN
            if unknown:
                raise RenderError(f"{p}: unsupported kustomization fields {sorted(unknown)} (render.py implements {sorted(KNOWN)})")
            return p, k
    raise RenderError(f"{d}: no kustomization.yaml")


def load_docs(path):
    with open(path) as f:
        return [d for d in yaml.safe_load_all(f) if d]


def key_of(o):
    return (o.get("kind"), o.get("metadata", {}).get("name"))


def generate(d, gens, kind, opts, existing):
    """configMapGenerator / secretGenerator entries onto `existing` (list of objects, in place)."""
    if gens and not (opts or {}).get("disableNameSuffixHash"):
        raise RenderError(f"{d}: name-suffix hashes are not implemented; set generatorOptions.disableNameSuffixHash: true")
    for g in gens or []:
        unknown = set(g) - {"name", "files", "literals", "behavior", "options"}
        if unknown:
            raise RenderError(f"{d}: unsupported generator fields {sorted(unknown)}")
        data = {}
        for spec in g.get("files", []):
            k, _, p = spec.partition("=") if "=" in spec else (os.path.basename(spec), "", spec)
            full = os.path.normpath(os.path.join(d, p))
            if not full.startswith(os.path.normpath(d) + os.sep):
                raise RenderError(f"{d}: generator file {p} is outside the kustomization directory (kustomize refuses it)")
            with open(full) as f:
                data[k] = f.read()
        for lit in g.get("literals", []):
            k, _, v = lit.partition("=")
            data[k] = v
        if kind == "Secret":
            data = {k: base64.b64encode(v.encode()).decode() for k, v in data.items()}
        behavior = g.get("behavior", "create")
        found = [o for o in existing if key_of(o) == (kind, g["name"])]
        if behavior == "create":
            if found:
                raise RenderError(f"{d}: {kind} {g['name']} already exists (use behavior: replace or merge)")
            obj = {"apiVersion": "v1", "kind": kind, "metadata": {"name": g["name"]}, "data": data}
            if kind == "Secret":
                obj["type"] = "Opaque"
            existing.append(obj)
        elif behavior in ("replace", "merge"):
            if not found:
                raise RenderError(f"{d}: {kind} {g['name']} to {behavior} does not exist")
            if behavior == "replace":
                found[0]["data"] = data
            else:
                found[0].setdefault("data", {}).update(data)
        else:
            raise RenderError(f"{d}: unknown generator behavior {behavior}")


def merge_key(field, items):
    if field == "ports":
        return "containerPort" if all(isinstance(i, dict) and "containerPort" in i for i in items) else "port"
    return MERGE_KEYS.get(field)


def sm_merge(base, patch, field=None):
    """Strategic merge of `patch` onto `base` (returns the result; inputs untouched)."""
    if isinstance(patch, dict):
        directive = patch.get("$patch")
        clean = {k: v for k, v in patch.items() if k != "$patch"}
        if directive == "replace":
            return copy.deepcopy(clean)
        if directive not in (None, "merge"):
            raise RenderError(f"unsupported $patch: {directive}")
        if not isinstance(base, dict):
            return copy.deepcopy(clean)
        out = copy.deepcopy(base)
        for k, v in clean.items():
            if v is None:
                out.pop(k, None)
            elif isinstance(v, dict) and v.get("$patch") == "delete":
                out.pop(k, None)
            elif k in out:
                out[k] = sm_merge(out[k], v, k)
            else:
                out[k] = sm_merge(None, v, k)
        return out
    if isinstance(patch, list):
        key = merge_key(field, patch)
        if key is None or not isinstance(base, list) or not all(isinstance(i, dict) and key in i for i in patch):
            return [sm_merge(None, i) if isinstance(i, dict) else copy.deepcopy(i) for i in patch]
        out = copy.deepcopy(base)
        new = []
        for item in patch:
            idx = next((n for n, b in enumerate(out) if isinstance(b, dict) and b.get(key) == item[key]), None)
            if item.get("$patch") == "delete":
                if idx is not None:
                    out.pop(idx)
            elif idx is None:
                new.append(sm_merge(None, item))
            else:
                out[idx] = sm_merge(out[idx], item)
        # kustomize (kyaml) puts items only the patch has before the existing ones.
        return new + out
    return copy.deepcopy(patch)


def apply_patches(d, patches, objs):
    for p in patches or []:
        unknown = set(p) - {"path", "patch"}
        if unknown:
            raise RenderError(f"{d}: unsupported patch fields {sorted(unknown)} (strategic-merge patches by path or inline only)")
        docs = load_docs(os.path.join(d, p["path"])) if "path" in p else [yaml.safe_load(p["patch"])]
        for doc in docs:
            if not isinstance(doc, dict) or "kind" not in doc:
                raise RenderError(f"{d}: patch {p} is not a strategic-merge patch (JSON 6902 is not implemented)")
            targets = [n for n, o in enumerate(objs) if key_of(o) == key_of(doc)]
            if len(targets) != 1:
                raise RenderError(f"{d}: patch for {key_of(doc)} matches {len(targets)} objects")
            objs[targets[0]] = sm_merge(objs[targets[0]], doc)


def pod_specs(o):
    spec = o.get("spec", {})
    if o.get("kind") == "Pod":
        yield spec
    elif "template" in spec:
        yield spec["template"].get("spec", {})
    if o.get("kind") == "CronJob":
        yield spec.get("jobTemplate", {}).get("spec", {}).get("template", {}).get("spec", {})


def apply_images(d, images, objs):
    for img in images or []:
        unknown = set(img) - {"name", "newName", "newTag", "digest"}
        if unknown:
            raise RenderError(f"{d}: unsupported images fields {sorted(unknown)}")
        for o in objs:
            for ps in pod_specs(o):
                for c in ps.get("containers", []) + ps.get("initContainers", []):
                    ref = c.get("image", "")
                    name, tag, digest = split_image(ref)
                    if name != img["name"]:
                        continue
                    name = img.get("newName", name)
                    if "digest" in img:
                        c["image"] = f"{name}@{img['digest']}"
                    else:
                        t = img.get("newTag", tag)
                        c["image"] = name + (f":{t}" if t else "") + (f"@{digest}" if digest and "newTag" not in img else "")


def split_image(ref):
    """(name, tag, digest) of an image reference; a registry port is not a tag."""
    name, _, digest = ref.partition("@")
    slash = name.rfind("/")
    colon = name.rfind(":")
    tag = ""
    if colon > slash:
        name, tag = name[:colon], name[colon + 1:]
    return name, tag, digest


def render(d, component=False, base_objs=None):
    d = os.path.abspath(d)
    path, k = load_kustomization(d)
    is_component = k.get("kind") == "Component"
    if is_component != component:
        raise RenderError(f"{path}: kind {k.get('kind')} used as {'a component' if component else 'a resource'}")
    objs = base_objs if component else []
    for r in k.get("resources", []):
        full = os.path.join(d, r)
        if os.path.isdir(full):
            objs.extend(render(full))
        else:
            objs.extend(load_docs(full))
    for c in k.get("components", []):
        objs = render(os.path.join(d, c), component=True, base_objs=objs)
    opts = k.get("generatorOptions")
    generate(d, k.get("configMapGenerator"), "ConfigMap", opts, objs)
    generate(d, k.get("secretGenerator"), "Secret", opts, objs)
    apply_patches(d, k.get("patches"), objs)
    apply_images(d, k.get("images"), objs)
    if "namespace" in k:
        for o in objs:
            if o.get("kind") not in CLUSTER_SCOPED:
                o.setdefault("metadata", {})["namespace"] = k["namespace"]
    seen = set()
    for o in objs:
        kn = (key_of(o), o.get("metadata", {}).get("namespace"))
        if kn in seen:
            raise RenderError(f"{path}: duplicate object {kn}")
        seen.add(kn)
    return objs


class _Dumper(yaml.SafeDumper):
    pass


def _str(dumper, s):
    # Files from generators (learner.toml, job.toml) stay readable as block literals.
    return dumper.represent_scalar("tag:yaml.org,2002:str", s, style="|" if "\n" in s else None)


_Dumper.add_representer(str, _str)


def same_objects(ours, theirs):
    """Differences between two renderings, object by object (order of objects ignored)."""
    key = lambda o: (o.get("kind"), o.get("metadata", {}).get("namespace"), o.get("metadata", {}).get("name"))
    a, b = {key(o): o for o in ours}, {key(o): o for o in theirs}
    diffs = [f"only in render.py: {k}" for k in a.keys() - b.keys()] + [f"only in kustomize: {k}" for k in b.keys() - a.keys()]
    diffs += [f"differs: {k}" for k in a.keys() & b.keys() if a[k] != b[k]]
    return sorted(diffs)


def main():
    args = sys.argv[1:]
    compare = None
    if len(args) == 3 and args[0] == "--same-as":
        compare, args = args[1], args[2:]
    if len(args) != 1:
        sys.exit("usage: render.py [--same-as KUSTOMIZE_OUTPUT.yaml] KUSTOMIZATION_DIR > rendered.yaml")
    try:
        objs = render(args[0])
    except (RenderError, OSError, yaml.YAMLError) as e:
        sys.exit(f"render.py: {e}")
    objs.sort(key=lambda o: 0 if o.get("kind") == "Namespace" else 1)
    if compare:
        # Cross-check against `kubectl kustomize` where kubectl exists.
        diffs = same_objects(objs, load_docs(compare))
        for d in diffs:
            print(f"render.py vs kustomize: {d}", file=sys.stderr)
        sys.exit(1 if diffs else 0)
    yaml.dump_all(objs, sys.stdout, Dumper=_Dumper, sort_keys=False, default_flow_style=False)


if __name__ == "__main__":
    main()
