#!/usr/bin/env bash
# Validate the Kubernetes manifests of deploy/k8s without a cluster: every object against the
# OpenAPI schemas of every Kubernetes version that kubernetes-validate (PyPI) bundles, strictly
# (an unknown field is an error, as `kubectl apply` rejects it), and kustomization.yaml, which
# is kustomize's input and not a Kubernetes object, by its own checks: its kind and apiVersion,
# known fields only, every manifest of the folder listed in `resources` and every listed one
# present, and every `images` entry naming an image that a container uses (else `kustomize edit
# set image` would change nothing).
#
#   scripts/validate-k8s.sh [--venv DIR]
#
#   --venv DIR   the Python virtual environment that holds kubernetes-validate (default:
#                target/validate-k8s under the repository root); created, and the pinned
#                version installed with pip, when it does not hold that version
#
# Needs python3 with its venv module, and PyPI once to install. The validation itself reads
# only the schemas inside the package.
#
# Exit status: 0 when everything is valid, 1 when something is not, 2 on bad usage.
set -euo pipefail

usage() { sed -n '2,/^set -euo pipefail/p' "$0" | sed '$d; s/^# \{0,1\}//'; }
die() { echo "validate-k8s: error: $*" >&2; exit 1; }
bad_usage() { usage >&2; echo "validate-k8s: error: $*" >&2; exit 2; }

repo=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=$repo/target/validate-k8s
while (($#)); do
  case $1 in
    --venv) (($# >= 2)) || bad_usage "--venv needs a DIR"; venv=$2; shift ;;
    --venv=*) venv=${1#*=} ;;
    -h | --help) usage; exit 0 ;;
    *) bad_usage "unexpected argument $1" ;;
  esac
  shift
done
dir=$repo/deploy/k8s
# Pinned, so that a new release (new schemas, new Kubernetes versions) changes the verdict only
# when this line changes.
version=1.37.0

# --- kubernetes-validate in its own environment -----------------------------------------------
validator=$venv/bin/kubernetes-validate
if [[ $("$validator" --version 2>/dev/null || true) != "$version" ]]; then
  command -v python3 >/dev/null 2>&1 || die "python3 is needed (with its venv module)"
  echo "validate-k8s: installing kubernetes-validate $version into $venv" >&2
  python3 -m venv "$venv" || die "python3 -m venv $venv failed (Debian: apt-get install python3-venv)"
  "$venv/bin/pip" install --quiet --disable-pip-version-check "kubernetes-validate==$version" ||
    die "pip could not install kubernetes-validate==$version"
fi

failed=0
# --- kustomization.yaml -----------------------------------------------------------------------
# Prints its problems, with status 1 when there are any.
if ! "$venv/bin/python" - "$dir" <<'PY'; then failed=1; else echo "validate-k8s: kustomization.yaml: ok"; fi
import os
import sys

import yaml

d = sys.argv[1]
problems = []
with open(os.path.join(d, "kustomization.yaml")) as f:
    k = yaml.safe_load(f) or {}
if k.get("apiVersion") != "kustomize.config.k8s.io/v1beta1" or k.get("kind") != "Kustomization":
    problems.append("kind/apiVersion: want Kustomization, kustomize.config.k8s.io/v1beta1")
# The fields of kustomize's Kustomization (v1beta1); anything else is most likely a typo.
known = {
    "apiVersion", "kind", "metadata", "resources", "components", "crds", "namespace",
    "namePrefix", "nameSuffix", "commonLabels", "labels", "commonAnnotations", "images",
    "replicas", "patches", "patchesStrategicMerge", "patchesJson6902", "configMapGenerator",
    "secretGenerator", "generatorOptions", "vars", "replacements", "generators",
    "transformers", "validators", "openapi", "buildMetadata", "helmCharts", "helmGlobals",
    "sortOptions", "configurations", "bases",
}
problems += [f"unknown field {key!r}" for key in sorted(set(k) - known)]
resources = k.get("resources") or []
for r in resources:
    if not os.path.isfile(os.path.join(d, r)):
        problems.append(f"resources: {r} does not exist")
manifests = sorted(
    f for f in os.listdir(d) if f.endswith((".yaml", ".yml")) and f != "kustomization.yaml"
)
problems += [f"{m} is not listed in resources" for m in manifests if m not in resources]
# Image names the containers use, without tag or digest.
used = set()
for r in resources:
    path = os.path.join(d, r)
    if not os.path.isfile(path):
        continue
    with open(path) as f:
        for doc in yaml.safe_load_all(f):
            pod = ((doc or {}).get("spec") or {}).get("template", {}).get("spec", {})
            for c in pod.get("containers", []) + pod.get("initContainers", []):
                image = c.get("image", "").split("@")[0]
                last = image.rsplit("/", 1)[-1]
                used.add(image.rsplit(":", 1)[0] if ":" in last else image)
for i in k.get("images") or []:
    if i.get("name") not in used:
        problems.append(f"images: no container uses the image {i.get('name')!r} (used: {sorted(used)})")
for p in problems:
    print(f"validate-k8s: kustomization.yaml: {p}")
sys.exit(1 if problems else 0)
PY

# --- every object against every bundled Kubernetes version ------------------------------------
mapfile -t versions < <("$venv/bin/python" -c '
from kubernetes_validate.utils import all_versions
for v in sorted(set(all_versions()), key=lambda v: tuple(map(int, v.split(".")))):
    print(v)')
((${#versions[@]})) || die "kubernetes-validate $version lists no Kubernetes versions"
# Every manifest of the folder, listed in kustomization.yaml or not (its check says which).
paths=()
for f in "$dir"/*.yaml "$dir"/*.yml; do
  if [[ -f $f && ${f##*/} != kustomization.yaml ]]; then paths+=("$f"); fi
done
((${#paths[@]})) || die "no manifests in $dir"
for v in "${versions[@]}"; do
  if out=$("$validator" --strict --kubernetes-version "$v" "${paths[@]}" 2>&1); then
    echo "validate-k8s: Kubernetes $v: ok"
  else
    failed=1
    echo "validate-k8s: Kubernetes $v:"
  fi
  # The errors and warnings, without the line per object that passed.
  grep -v '^INFO' <<<"$out" | sed "s|$dir/||; s/^/    /" || true
done
if ((failed)); then
  echo "validate-k8s: FAIL"
  exit 1
fi
echo "validate-k8s: PASS: ${#paths[@]} manifests and kustomization.yaml, Kubernetes ${versions[0]} to ${versions[-1]}"
