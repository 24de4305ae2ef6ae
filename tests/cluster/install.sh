#!/usr/bin/env bash
# Installs what the `cluster` tests run (`pytest --cluster`, docs/CLUSTER.md): Debian's SLURM (slurmctld, slurmd,
# slurmdbd, the client commands), munge, MariaDB (slurmdbd's accounting store, which `sacct` reads), PostgreSQL (the
# MLflow tracking server's backend store), and this project's `cluster` extra (the Snakemake SLURM executor plugin
# and PostgreSQL's Python driver) into the active Python environment. The tests themselves install nothing.
#
# Needs root and apt-get; run it from the repository root with the project's virtual environment active:
#   . .venv/bin/activate && sudo -E env PATH="$PATH" bash tests/cluster/install.sh
# Nothing is started here and no service is enabled: tests/cluster/engines.py starts every engine on loopback and
# stops it again.
set -euo pipefail
cd "$(dirname "$0")/../.."

if [ "$(id -u)" -ne 0 ]; then
  echo "tests/cluster/install.sh: needs root (apt-get installs SLURM, munge, MariaDB and PostgreSQL)" >&2
  exit 2
fi
if ! command -v apt-get >/dev/null; then
  echo "tests/cluster/install.sh: needs apt-get (Debian or Ubuntu); install slurmctld, slurmd, slurmdbd, munge," \
       "mariadb-server and postgresql with this system's package manager instead" >&2
  exit 2
fi

PACKAGES=(slurmctld slurmd slurmdbd slurm-client munge mariadb-server postgresql)
absent=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || absent+=("$p")
done
if [ "${#absent[@]}" -gt 0 ]; then
  echo "installing ${absent[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q
  # The packages' own services are not wanted: the tests start the engines themselves, on free loopback ports.
  if [ ! -e /usr/sbin/policy-rc.d ]; then
    printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d
    trap 'rm -f /usr/sbin/policy-rc.d' EXIT
  fi
  apt-get install -y -q --no-install-recommends "${PACKAGES[@]}"
else
  echo "SLURM, munge, MariaDB and PostgreSQL are installed"
fi

# The locked environment first (a no-op after the README's install), so the cluster extra adds its packages to it
# without moving a pin.
python3 -m pip install -q --require-hashes -r requirements.lock
python3 -m pip install -q -e ".[cluster]"
echo "cluster engines and the cluster extra are installed"
