"""A throwaway QEMU guest with a stock Debian kernel, for real SocketCAN on hosts without CAN.

The host kernel here has no CAN support at all. The guest boots Debian's own kernel (fetched with
``apt-get download`` at first use and cached outside the repository, never installed on the host)
with a busybox initramfs, loads the CAN modules, creates vcan0 and runs a command in the host's own
userland, shared read-only over 9p: the same Python, virtualenv, project and can-utils. The project
folder and a results folder are shared writable. Facts this relies on: ``../shared/notes/vcan-vm.md``.
"""

from __future__ import annotations

import gzip
import os
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

MODULES = (
    "virtio_ring",
    "virtio",
    "virtio_pci_modern_dev",
    "virtio_pci_legacy_dev",
    "virtio_pci",  # the bus
    "netfs",
    "fscache",
    "9pnet",
    "9pnet_virtio",
    "9p",  # the host's files over 9p
    "can",
    "can-raw",
    "can-bcm",
    "can-dev",
    "vcan",  # SocketCAN
    "can-j1939",  # the kernel's J1939 stack (a real J1939 peer for DM1 and its transport protocol)
)
EXIT_MARK = "CMCAN-VM-EXIT="

INIT = r"""#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin
mount -t proc proc /proc
mount -t sysfs sys /sys
mount -t devtmpfs dev /dev
for m in $(cat /modules.order); do insmod /mods/$m.ko || echo "cmcan-vm: insmod $m failed"; done
for x in $(cat /proc/cmdline); do
  case "$x" in cmcan.project=*) PROJECT="${x#cmcan.project=}";; cmcan.results=*) RESULTS="${x#cmcan.results=}";; esac
done
O=trans=virtio,version=9p2000.L,msize=262144,cache=loose
mkdir -p /host
mount -t 9p -o $O,ro hostroot /host || { echo "cmcan-vm: cannot mount the host root"; poweroff -f; }
mount -t proc proc /host/proc
mount -t sysfs sys /host/sys
mount -t devtmpfs dev /host/dev
mkdir -p /host/dev/shm /host/dev/pts
mount -t tmpfs shm /host/dev/shm
mount -t tmpfs tmp /host/tmp
mount -t tmpfs run /host/run
for share in project:$PROJECT results:$RESULTS; do
  tag="${share%%:*}"; dir="${share#*:}"
  [ -d "/host$dir" ] || mkdir -p "/host$dir"
  mount -t 9p -o $O "$tag" "/host$dir" || echo "cmcan-vm: cannot mount $tag at $dir"
done
for v in vcan0 vcan1; do ip link add dev $v type vcan && ip link set up $v || echo "cmcan-vm: no $v"; done
chroot /host /bin/sh "$RESULTS/run.sh" </dev/null
echo "CMCAN-VM-EXIT=$?"
sync
poweroff -f
"""


class VmError(RuntimeError):
    """The VM could not be prepared or booted; ``str()`` says which step and why."""


@dataclass(frozen=True)
class VmResult:
    exit_code: int
    console: str
    wall_s: float


def cache_dir() -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "cmcan-vcan"


def _run(cmd: list[str], what: str, cwd: Path | None = None) -> str:
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=600)
    except FileNotFoundError:
        raise VmError(f"{what}: {cmd[0]} is not installed") from None
    if res.returncode != 0:
        raise VmError(f"{what}: {' '.join(cmd)} failed: {res.stderr.strip()[-400:]}")
    return res.stdout


def kernel_package() -> str:
    """The exact kernel package Debian's linux-image-amd64 depends on (e.g. linux-image-6.1.0-56-amd64)."""
    out = _run(["apt-cache", "depends", "linux-image-amd64"], "finding the stock kernel")
    m = re.search(r"Depends:\s*(linux-image-[0-9][^\s]*-amd64)", out)
    if not m:
        raise VmError("finding the stock kernel: apt-cache names no linux-image-*-amd64 (run apt-get update?)")
    return m.group(1)


def ensure_kernel() -> tuple[Path, Path]:
    """(vmlinuz, module folder) in the cache; downloads and unpacks the kernel at first use."""
    root = cache_dir()
    done = [r for r in sorted(root.glob("*/ready")) if all((r.parent / "mods" / f"{m}.ko").exists() for m in MODULES)]
    if done:  # a cache from before a module was added is unpacked again
        d = done[-1].parent
        return d / "vmlinuz", d / "mods"
    pkg = kernel_package()
    version = pkg.removeprefix("linux-image-")
    d = root / version
    d.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        _run(["apt-get", "download", pkg], f"downloading {pkg}", cwd=Path(tmp))
        debs = list(Path(tmp).glob("*.deb"))
        if not debs:
            raise VmError(f"downloading {pkg}: no .deb arrived")
        unpack = Path(tmp) / "x"
        _run(["dpkg", "-x", str(debs[0]), str(unpack)], f"unpacking {debs[0].name}")
        shutil.copy(unpack / "boot" / f"vmlinuz-{version}", d / "vmlinuz")
        mods = d / "mods"
        mods.mkdir(exist_ok=True)
        tree = unpack / "lib" / "modules" / version
        for name in MODULES:
            found = list(tree.rglob(f"{name}.ko"))
            if not found:
                raise VmError(f"{pkg}: module {name}.ko not found")
            shutil.copy(found[0], mods / f"{name}.ko")
    (d / "ready").write_text(pkg + "\n")
    return d / "vmlinuz", d / "mods"


def build_initramfs(mods: Path, out: Path) -> Path:
    busybox = shutil.which("busybox")
    if busybox is None:
        raise VmError("building the initramfs: busybox is not installed (Debian package busybox-static)")
    with tempfile.TemporaryDirectory() as tmp:
        r = Path(tmp)
        for sub in ("bin", "proc", "sys", "dev", "mods", "host"):
            (r / sub).mkdir()
        shutil.copy(busybox, r / "bin" / "busybox")
        (r / "bin" / "sh").symlink_to("busybox")
        for name in MODULES:
            shutil.copy(mods / f"{name}.ko", r / "mods" / f"{name}.ko")
        (r / "modules.order").write_text("\n".join(MODULES) + "\n")
        (r / "init").write_text(INIT)
        (r / "init").chmod(0o755)
        files = sorted(str(p.relative_to(r)) for p in r.rglob("*"))
        cpio = subprocess.run(
            [busybox, "cpio", "-o", "-H", "newc"], input=("\n".join(files) + "\n").encode(), capture_output=True, cwd=r
        )
        if cpio.returncode != 0:
            raise VmError(f"building the initramfs: cpio failed: {cpio.stderr.decode()[-300:]}")
        out.write_bytes(gzip.compress(cpio.stdout, compresslevel=1))
    return out


def run_in_vm(
    script: str, project: Path, results: Path, timeout_s: float = 600.0, memory_mb: int = 1024, echo: bool = True
) -> VmResult:
    """Boot the guest, run ``script`` (shell) inside in the host's userland, return its exit code."""
    qemu = shutil.which("qemu-system-x86_64")
    if qemu is None:
        raise VmError("qemu-system-x86_64 is not installed (Debian package qemu-system-x86)")
    vmlinuz, mods = ensure_kernel()
    results.mkdir(parents=True, exist_ok=True)
    initrd = build_initramfs(mods, results / "initramfs.cpio.gz")
    (results / "run.sh").write_text("#!/bin/sh\n" + script + "\n")
    project, results = project.resolve(), results.resolve()
    for p in (project, results):
        if " " in str(p):
            raise VmError(f"{p}: the VM shares folders by path and cannot take one with spaces")
    cmd = [
        qemu,
        "-accel",
        "tcg,thread=multi",
        "-cpu",
        "max",
        "-smp",
        "2",
        "-m",
        str(memory_mb),
        "-nographic",
        "-no-reboot",
        "-nic",
        "none",
        "-kernel",
        str(vmlinuz),
        "-initrd",
        str(initrd),
        "-append",
        f"console=ttyS0 quiet loglevel=3 panic=-1 cmcan.project={project} cmcan.results={results}",
        "-virtfs",
        "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap",
        "-virtfs",
        f"local,path={project},mount_tag=project,security_model=none,multidevs=remap",
        "-virtfs",
        f"local,path={results},mount_tag=results,security_model=none",
    ]
    t0 = time.monotonic()
    lines: list[str] = []
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True, errors="replace"
    )
    assert proc.stdout is not None
    try:
        deadline = t0 + timeout_s
        for line in proc.stdout:
            lines.append(line)
            if echo:
                sys.stdout.write("[vm] " + line)
                sys.stdout.flush()
            if time.monotonic() > deadline:
                raise VmError(f"the VM ran longer than {timeout_s:.0f} s")
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    console = "".join(lines)
    m = re.search(EXIT_MARK + r"(\d+)", console)
    if not m:
        raise VmError("the VM stopped without reporting an exit code; console tail:\n" + console[-2000:])
    return VmResult(int(m.group(1)), console, time.monotonic() - t0)


def guest_script(project: Path, results: Path, command: list[str], env: dict[str, str] | None = None) -> str:
    """The shell script the guest runs: the host's environment essentials, then ``command``."""
    keep = {k: os.environ[k] for k in ("PATH", "VIRTUAL_ENV", "LANG", "CI") if k in os.environ}
    keep.update(
        HOME="/tmp/home",
        PYTHONDONTWRITEBYTECODE="1",
        CMCAN_IN_VM="1",
        TMPDIR="/tmp",
        OMP_NUM_THREADS="1",
        **(env or {}),
    )
    exports = "\n".join(f"export {k}={shlex.quote(v)}" for k, v in keep.items())
    return f"""{exports}
mkdir -p /tmp/home
cd {shlex.quote(str(project))} || exit 97
{" ".join(shlex.quote(c) for c in command)}
"""
