"""dct-hil doctor (rt_loop/tools/doctor.py): every item's verdicts on fake /proc and
/sys trees, odd files, the report, and the command line.

The baseline tree is a well set-up bench PC (PREEMPT_RT, CPU 3 of four
isolated, performance governor, deep idle states off, a PCIe CAN card whose
interrupt stays off CPU 3); each test changes what it is about. The ip JSON
and the floor measurement are injected; one short real floor run checks the
wiring to the C loop (its figures are never judged).
"""

import gzip
import json
import shutil
import struct

import pytest

from dct_hil import cli
from rt_loop.floor import FloorError
from rt_loop.tools import doctor
from rt_loop.tools.doctor import parse_cpulist, run_doctor

IP_CAN0 = {
    "ifname": "can0", "flags": ["NOARP", "UP", "LOWER_UP", "ECHO"], "operstate": "UP",
    "linkinfo": {"info_kind": "can", "info_data": {
        "state": "ERROR-ACTIVE", "berr_counter": {"tx": 0, "rx": 0},
        "bittiming": {"bitrate": 1000000, "sample_point": "0.750"}}},
}

GOOD_FLOOR = {"samples": 20000, "p50_us": 3.0, "p90_us": 4.0, "p99_us": 6.0, "p99_9_us": 12.0,
              "max_us": 30.0, "mean_us": 3.2, "late_wakeups": 0, "late_threshold_us": 500.0,
              "skipped": 0, "rt_policy_ok": True, "memory_locked": True, "affinity_ok": True}


class FakePC:
    """A /proc and /sys tree below ``root``."""

    def __init__(self, root):
        self.root = root
        self.ip = {"can0": [json.loads(json.dumps(IP_CAN0))]}
        self.floor_calls = []
        self.floor = {None: dict(GOOD_FLOOR), 0: dict(GOOD_FLOOR)}
        w = self.write
        w("proc/cmdline", "BOOT_IMAGE=/vmlinuz root=/dev/sda1 ro isolcpus=3 nohz_full=3 "
          "rcu_nocbs=3 irqaffinity=0-2 quiet\n")
        w("proc/sys/kernel/version", "#1 SMP PREEMPT_RT Debian 6.1.76-1 (2024-02-01)\n")
        w("proc/sys/kernel/osrelease", "6.1.0-18-rt-amd64\n")
        w("proc/sys/kernel/sched_rt_runtime_us", "950000\n")
        w("proc/sys/kernel/sched_rt_period_us", "1000000\n")
        w("sys/kernel/realtime", "1\n")
        w("sys/kernel/mm/transparent_hugepage/enabled", "always madvise [never]\n")
        w("proc/swaps", "Filename\t\t\t\tType\t\tSize\t\tUsed\t\tPriority\n")
        w("proc/self/status", "Name:\tdct-hil\nUid:\t0\t0\t0\t0\nGid:\t0\t0\t0\t0\n"
          "CapInh:\t0000000000000000\nCapEff:\t000001ffffffffff\n")
        self.limits(memlock="8388608", rtprio="0")
        self.write_bytes("dev/cpu_dma_latency", struct.pack("=i", 2_000_000_000))
        cpu = "sys/devices/system/cpu"
        w(f"{cpu}/online", "0-3\n")
        w(f"{cpu}/isolated", "3\n")
        w(f"{cpu}/nohz_full", "3\n")
        w(f"{cpu}/smt/control", "notsupported\n")
        for n in range(4):
            w(f"{cpu}/cpu{n}/cpufreq/scaling_governor", "performance\n")
            w(f"{cpu}/cpu{n}/topology/thread_siblings_list", f"{n}\n")
            for k, (name, latency, disable) in enumerate(
                    (("POLL", 0, 0), ("C1", 1, 0), ("C1E", 10, 0), ("C6", 133, 1))):
                self.idle_state(n, k, name, latency, disable)
        # a PCIe CAN card: can0 -> its PCI device with one MSI interrupt, IRQ 45
        pci = "sys/devices/pci0000:00/0000:00:1c.0"
        w(f"{pci}/msi_irqs/45", "msi\n")
        (root / "sys/bus/pci/drivers/peak_pci").mkdir(parents=True)
        self.link(f"{pci}/driver", "../../../bus/pci/drivers/peak_pci")
        self.netdev("can0", device="../../../devices/pci0000:00/0000:00:1c.0")
        w("proc/interrupts", "           CPU0       CPU1       CPU2       CPU3\n"
          "  0:         10          0          0          0   IO-APIC   2-edge      timer\n"
          " 45:       1200          0          0          0   PCI-MSI 1234-edge      can0\n"
          "LOC:      23983      17412      12000        100   Local timer interrupts\n")
        w("proc/irq/45/smp_affinity_list", "0-2\n")
        w("proc/irq/0/smp_affinity_list", "0-3\n")

    def write(self, path, text):
        self.write_bytes(path, text.encode())

    def write_bytes(self, path, data):
        p = self.root / path
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)

    def remove(self, path):
        (self.root / path).unlink()

    def link(self, path, target):
        p = self.root / path
        p.parent.mkdir(parents=True, exist_ok=True)
        p.symlink_to(target)

    def limits(self, memlock="unlimited", rtprio="0", memlock_hard=None, rtprio_hard=None):
        rows = [("Max cpu time", "unlimited", "unlimited", "seconds"),
                ("Max locked memory", memlock, memlock_hard or memlock, "bytes"),
                ("Max realtime priority", rtprio, rtprio_hard or rtprio, ""),
                ("Max realtime timeout", "unlimited", "unlimited", "us")]
        self.write("proc/self/limits", "Limit                     Soft Limit           Hard Limit"
                   "           Units     \n" + "".join(f"{a:<26}{b:<21}{c:<21}{d:<10}\n"
                                                       for a, b, c, d in rows))

    def caps(self, cap_eff, uid=1000):
        self.write("proc/self/status", f"Name:\tdct-hil\nUid:\t{uid}\t{uid}\t{uid}\t{uid}\n"
                   f"CapEff:\t{cap_eff:016x}\n")

    def idle_state(self, cpu, k, name, latency_us, disable):
        base = f"sys/devices/system/cpu/cpu{cpu}/cpuidle/state{k}"
        self.write(f"{base}/name", f"{name}\n")
        self.write(f"{base}/latency", f"{latency_us}\n")
        self.write(f"{base}/disable", f"{disable}\n")

    def netdev(self, name, type_=280, flags="0x40c1", operstate="up", txqueuelen=1000,
               device=None, **stats):
        base = f"sys/class/net/{name}"
        self.write(f"{base}/type", f"{type_}\n")
        self.write(f"{base}/flags", f"{flags}\n")
        self.write(f"{base}/operstate", f"{operstate}\n")
        self.write(f"{base}/tx_queue_len", f"{txqueuelen}\n")
        for counter in ("rx_dropped", "tx_dropped", "rx_errors", "tx_errors"):
            self.write(f"{base}/statistics/{counter}", f"{stats.get(counter, 0)}\n")
        if device:
            self.link(f"{base}/device", device)

    def config(self, text, gz=True):
        if gz:
            self.write_bytes("proc/config.gz", gzip.compress(text.encode()))
        else:
            self.write("boot/config-6.1.0-18-rt-amd64", text)

    def ip_link(self, name):
        if name not in self.ip:
            raise OSError(f'Device "{name}" does not exist.')
        return self.ip[name]

    def measure(self, duration_s, rate_hz, priority, cpu, pm_qos_us=None):
        self.floor_calls.append((duration_s, rate_hz, priority, cpu, pm_qos_us))
        fig = dict(self.floor[pm_qos_us])
        fig["pm_qos"] = {"requested_us": pm_qos_us, "held": pm_qos_us is not None,
                         "error": None, "path": "/dev/cpu_dma_latency"}
        return fig

    def run(self, **kw):
        kw.setdefault("cpu", 3)
        kw.setdefault("channel", "can0")
        kw.setdefault("floor", False)
        return run_doctor(str(self.root), ip_link=self.ip_link, measure=self.measure, **kw)

    def item(self, key, **kw):
        return self.run(**kw).item(key)


@pytest.fixture
def pc(tmp_path):
    return FakePC(tmp_path / "root")


def assert_not_ok(item, verdict, *fix_words):
    assert item.verdict == verdict, item
    assert item.fix, item
    for word in fix_words:
        assert word in item.fix, item.fix


NONE_DYNAMIC_CONFIG = ("CONFIG_PREEMPT_BUILD=y\nCONFIG_PREEMPT_NONE=y\n"
                       "# CONFIG_PREEMPT_VOLUNTARY is not set\n# CONFIG_PREEMPT is not set\n"
                       "CONFIG_PREEMPT_COUNT=y\nCONFIG_PREEMPTION=y\nCONFIG_PREEMPT_DYNAMIC=y\n")


def stock_kernel(pc, version="#1 SMP PREEMPT_DYNAMIC Debian 6.1.76-1 (2024-02-01)"):
    """A Debian stock kernel: not RT, debugfs not readable."""
    pc.remove("sys/kernel/realtime")
    pc.write("proc/sys/kernel/version", version + "\n")
    (pc.root / "sys/kernel/debug/sched/preempt").mkdir(parents=True)   # reading it fails


# ------------------------------------------------------------------ baseline
def test_a_well_set_up_pc_is_ok_everywhere(pc):
    report = pc.run(floor=True, floor_s=2.0)
    assert {i.key: i.verdict for i in report.items} == {i.key: "ok" for i in report.items}
    assert len(report.items) == 13
    assert report.exit_code == 0
    assert all(i.fix is None for i in report.items)
    assert pc.floor_calls == [(2.0, 2000.0, 80, 3, None), (2.0, 2000.0, 80, 3, 0)]


def test_every_item_not_ok_has_a_fix(pc):
    stock_kernel(pc)
    pc.config(NONE_DYNAMIC_CONFIG)
    pc.write("proc/cmdline", "quiet\n")
    pc.write("sys/devices/system/cpu/isolated", "\n")
    pc.write("sys/kernel/mm/transparent_hugepage/enabled", "[always] madvise never\n")
    pc.caps(0)
    pc.write("proc/swaps", "Filename Type Size Used Priority\n/swapfile file 2097148 0 -2\n")
    pc.limits(memlock="65536", rtprio="0")
    report = pc.run(cpu=None)
    for item in report.items:
        if item.verdict in ("warn", "fail"):
            assert item.fix, item
    assert report.exit_code == 1


# ------------------------------------------------------------- preemption
def test_preemption_rt_from_sys_kernel_realtime(pc):
    item = pc.item("preemption")
    assert item.verdict == "ok"
    assert item.details["mode"] == "rt"
    assert "/sys/kernel/realtime" in item.details["decided_by"]
    assert "PREEMPT_RT" in item.finding


def test_preemption_rt_from_the_version_string(pc):
    pc.remove("sys/kernel/realtime")
    item = pc.item("preemption")
    assert item.verdict == "ok" and item.details["mode"] == "rt"
    assert "version string" in item.details["decided_by"]


def test_preemption_full_from_the_version_string(pc):
    stock_kernel(pc, "#1 SMP PREEMPT Fri Jan 5 2024")
    item = pc.item("preemption")
    assert item.details["mode"] == "full" and item.details["dynamic"] is False
    assert item.finding.startswith("full,")
    assert_not_ok(item, "warn", "linux-image-rt-amd64")
    assert "preempt=full" not in item.fix


def test_preemption_full_from_debugfs_on_a_dynamic_kernel(pc):
    stock_kernel(pc)
    (pc.root / "sys/kernel/debug/sched/preempt").rmdir()
    pc.write("sys/kernel/debug/sched/preempt", "none voluntary (full) lazy\n")
    pc.config(NONE_DYNAMIC_CONFIG)
    item = pc.item("preemption")
    assert item.details["mode"] == "full" and item.details["dynamic"] is True
    assert "/sys/kernel/debug/sched/preempt" in item.details["decided_by"]
    assert item.finding.startswith("full (dynamic)")
    assert_not_ok(item, "warn", "linux-image-rt")


def test_preemption_voluntary_from_the_boot_config(pc):
    stock_kernel(pc, "#1 SMP Debian 6.1.76-1")
    pc.config("CONFIG_PREEMPT_VOLUNTARY=y\n# CONFIG_PREEMPT_DYNAMIC is not set\n", gz=False)
    item = pc.item("preemption")
    assert item.details["mode"] == "voluntary" and item.details["dynamic"] is False
    assert "/boot/config-6.1.0-18-rt-amd64" in item.details["decided_by"]
    assert_not_ok(item, "warn", "apt-get install linux-image-rt-amd64")


def test_preemption_none_dynamic_from_config_gz(pc):
    """This machine: PREEMPT_DYNAMIC kernel, debugfs refused, CONFIG_PREEMPT_NONE=y."""
    stock_kernel(pc, "#1 SMP PREEMPT_DYNAMIC @0")
    pc.config(NONE_DYNAMIC_CONFIG)
    item = pc.item("preemption")
    assert item.finding.startswith("none (dynamic), decided by CONFIG_PREEMPT_NONE=y in "
                                   "/proc/config.gz")
    assert "/sys/kernel/debug/sched/preempt unreadable" in item.finding
    assert_not_ok(item, "warn", "linux-image-rt-amd64", "preempt=full")


def test_preemption_from_the_command_line_before_the_config(pc):
    stock_kernel(pc)
    pc.config(NONE_DYNAMIC_CONFIG)
    pc.write("proc/cmdline", "root=/dev/sda1 preempt=full quiet\n")
    item = pc.item("preemption")
    assert item.details["mode"] == "full" and item.details["dynamic"] is True
    assert item.details["decided_by"] == "preempt=full on the kernel command line"
    pc.write("proc/cmdline", "root=/dev/sda1 preempt=none\n")
    item = pc.item("preemption")
    assert item.finding.startswith("none (dynamic), decided by preempt=none")
    assert "preempt=full" in item.fix


def test_preemption_boot_option_ignored_without_dynamic_preemption(pc):
    stock_kernel(pc, "#1 SMP Debian")
    pc.config("CONFIG_PREEMPT_NONE=y\n# CONFIG_PREEMPT_DYNAMIC is not set\n")
    pc.write("proc/cmdline", "preempt=full\n")
    item = pc.item("preemption")
    assert item.details["mode"] == "none"
    assert "ignored" in item.finding


def test_preemption_unknown_when_nothing_says(pc):
    stock_kernel(pc, "#1 SMP Debian")
    pc.write_bytes("proc/config.gz", b"\x00\xffnot gzip")
    item = pc.item("preemption")
    assert item.finding.startswith("unknown:")
    assert "not gzip" in item.finding and "/boot/config-6.1.0-18-rt-amd64" in item.finding
    assert_not_ok(item, "warn", "linux-image-rt")


# ---------------------------------------------------------------- throttling
@pytest.mark.parametrize("runtime, verdict, words", [
    ("-1", "ok", ["never throttled"]),
    ("950000", "ok", ["safety net", "95%", "62%"]),
    ("1000000", "ok", ["no effective limit"]),
    ("500000", "warn", ["50%", "--spin-us 0"]),
    ("10000", "fail", ["1%"]),
    ("0", "fail", ["no CPU time"]),
])
def test_rt_throttling(pc, runtime, verdict, words):
    pc.write("proc/sys/kernel/sched_rt_runtime_us", runtime + "\n")
    item = pc.item("rt_throttling")
    assert item.verdict == verdict, item
    for word in words:
        assert word in item.finding + (item.fix or ""), item
    if verdict != "ok":
        assert "sysctl -w kernel.sched_rt_runtime_us=950000" in item.fix


def test_rt_throttling_need_follows_the_rate(pc):
    pc.write("proc/sys/kernel/sched_rt_runtime_us", "500000\n")
    assert pc.item("rt_throttling", rate_hz=500.0).verdict == "ok"   # 310 us of 2000 us
    assert pc.item("rt_throttling", priority=0).verdict == "ok"      # no spin without FIFO


# ----------------------------------------------------------------- isolation
def test_isolation_ok_when_the_loop_cpu_is_isolated(pc):
    item = pc.item("isolation")
    assert item.verdict == "ok"
    assert "CPU 3 is isolated" in item.finding and "irqaffinity=0-2" in item.finding


def test_isolation_none_at_all(pc):
    pc.write("proc/cmdline", "root=/dev/sda1 quiet\n")
    pc.write("sys/devices/system/cpu/isolated", "\n")
    pc.write("sys/devices/system/cpu/nohz_full", "(null)\n")
    item = pc.item("isolation", cpu=None)
    assert item.finding.startswith("no CPU isolated")
    assert_not_ok(item, "warn", "isolcpus=3 nohz_full=3 rcu_nocbs=3", "dct-hil serve --cpu 3")
    item = pc.item("isolation", cpu=1)
    assert "--cpu 1 is not isolated" in item.finding
    assert_not_ok(item, "warn", "isolcpus=1 nohz_full=1 rcu_nocbs=1", "--cpu 1")


def test_isolation_without_nohz_full_support_says_so(pc):
    pc.write("proc/cmdline", "quiet\n")
    pc.write("sys/devices/system/cpu/isolated", "\n")
    pc.remove("sys/devices/system/cpu/nohz_full")
    assert "CONFIG_NO_HZ_FULL" in pc.item("isolation").finding


def test_isolation_isolated_cpus_but_no_cpu_given(pc):
    item = pc.item("isolation", cpu=None)
    assert "no --cpu" in item.finding
    assert_not_ok(item, "warn", "dct-hil serve --cpu 3")


def test_isolation_cpu_mismatch(pc):
    item = pc.item("isolation", cpu=1)
    assert "--cpu 1 is not isolated" in item.finding
    assert_not_ok(item, "warn", "dct-hil serve --cpu 3")


def test_isolation_from_the_command_line_with_flags(pc):
    pc.write("sys/devices/system/cpu/isolated", "\n")
    pc.write("proc/cmdline", "isolcpus=nohz,domain,managed_irq,2-N nohz_full=2-3 "
             "rcu_nocbs=2-3 -- isolcpus=1\n")
    item = pc.item("isolation", cpu=2)
    assert item.verdict == "ok", item
    assert item.details["isolated"] == "2-3"


def test_isolation_ok_but_tick_still_there(pc):
    pc.write("proc/cmdline", "isolcpus=3\n")
    pc.write("sys/devices/system/cpu/nohz_full", "\n")
    item = pc.item("isolation")
    assert item.verdict == "ok"
    assert "nohz_full or rcu_nocbs" in item.finding


def test_a_cpu_that_is_not_online_is_an_error(pc):
    with pytest.raises(doctor.DoctorError, match="cpu 9 is not online.*0-3"):
        pc.run(cpu=9)


# ----------------------------------------------------------------- governor
def test_governor(pc):
    assert pc.item("governor").verdict == "ok"
    pc.write("sys/devices/system/cpu/cpu3/cpufreq/scaling_governor", "powersave\n")
    item = pc.item("governor")
    assert "powersave on CPU 3" in item.finding
    assert_not_ok(item, "warn", "cpupower frequency-set -g performance")
    pc.write("sys/devices/system/cpu/cpu3/cpufreq/scaling_governor", "performance\n")
    pc.write("sys/devices/system/cpu/cpu0/cpufreq/scaling_governor", "schedutil\n")
    assert pc.item("governor").verdict == "ok"                   # only the loop's CPU counts
    assert pc.item("governor", cpu=None).verdict == "warn"       # any CPU may run the loop


def test_governor_without_cpufreq_is_info(pc):
    for n in range(4):
        pc.remove(f"sys/devices/system/cpu/cpu{n}/cpufreq/scaling_governor")
        (pc.root / f"sys/devices/system/cpu/cpu{n}/cpufreq").rmdir()
    item = pc.item("governor", cpu=None)
    assert item.verdict == "info" and "no cpufreq on CPUs 0-3" in item.finding


# -------------------------------------------------------------- idle states
def test_idle_states_deep_state_enabled(pc):
    pc.idle_state(3, 3, "C6", 133, 0)
    item = pc.item("idle_states")
    assert "C6 (133 us) on CPU 3" in item.finding
    assert "C1E" not in item.finding                     # 10 us is the limit itself
    assert "PM QoS now: no request" in item.finding
    assert_not_ok(item, "warn", "/dev/cpu_dma_latency", "--pm-qos-us", "state3/disable")


def test_idle_states_ok_and_the_pm_qos_value(pc):
    pc.write_bytes("dev/cpu_dma_latency", struct.pack("=i", 0))
    item = pc.item("idle_states")
    assert item.verdict == "ok"
    assert "C1E, 10 us" in item.finding and "PM QoS now: 0 us" in item.finding
    assert item.details["pm_qos_now_us"] == 0


def test_idle_states_absent_is_info(pc):
    shutil.rmtree(pc.root / "sys/devices/system/cpu/cpu3/cpuidle")
    assert pc.item("idle_states").verdict == "info"


# ---------------------------------------------------------------------- SMT
def test_smt_sibling_not_isolated(pc):
    pc.write("sys/devices/system/cpu/smt/control", "on\n")
    pc.write("sys/devices/system/cpu/cpu3/topology/thread_siblings_list", "1,3\n")
    item = pc.item("smt")
    assert "shares its core with CPU 1" in item.finding
    assert_not_ok(item, "warn", "smt/control", "nosmt", "isolcpus=1,3")


def test_smt_sibling_isolated_too(pc):
    pc.write("sys/devices/system/cpu/smt/control", "on\n")
    pc.write("sys/devices/system/cpu/cpu3/topology/thread_siblings_list", "1,3\n")
    pc.write("sys/devices/system/cpu/isolated", "1,3\n")
    assert pc.item("smt").verdict == "ok"


def test_smt_without_cpu(pc):
    pc.write("sys/devices/system/cpu/smt/control", "on\n")
    for a, b in ((0, 2), (1, 3)):
        for n in (a, b):
            pc.write(f"sys/devices/system/cpu/cpu{n}/topology/thread_siblings_list", f"{a},{b}\n")
    item = pc.item("smt", cpu=None)
    assert "0,2 1,3" in item.finding
    assert_not_ok(item, "warn", "nosmt")
    pc.write("sys/devices/system/cpu/smt/control", "off\n")
    for n in range(4):
        pc.write(f"sys/devices/system/cpu/cpu{n}/topology/thread_siblings_list", f"{n}\n")
    assert pc.item("smt", cpu=None).verdict == "ok"


# ------------------------------------------------------------ CAN interrupts
def test_can_irq_away_from_the_loop(pc):
    item = pc.item("can_irq")
    assert item.verdict == "ok"
    assert "IRQ 45 on CPUs 0-2" in item.finding and item.details["driver"] == "peak_pci"


def test_can_irq_on_the_loop_cpu(pc):
    pc.write("proc/irq/45/smp_affinity_list", "0-3\n")
    item = pc.item("can_irq")
    assert "may run on the loop's CPU 3" in item.finding
    assert_not_ok(item, "warn", "echo 0 > /proc/irq/45/smp_affinity_list", "irqbalance")


def test_can_irq_found_by_driver_name_in_proc_interrupts(pc):
    pc.remove("sys/devices/pci0000:00/0000:00:1c.0/msi_irqs/45")
    pc.write("proc/interrupts", "           CPU0 CPU1 CPU2 CPU3\n"
             " 52:   5   0   0   0  IO-APIC  16-fasteoi   peak_pci\n")
    pc.write("proc/irq/52/smp_affinity_list", "3\n")
    item = pc.item("can_irq")
    assert item.verdict == "warn" and "IRQ 52 on CPU 3" in item.finding


def test_can_irq_of_a_usb_adapter_is_its_host_controller(pc):
    usb = "sys/devices/pci0000:00/0000:00:14.0"
    pc.write(f"{usb}/msi_irqs/120", "msi\n")
    (pc.root / f"{usb}/usb1/1-1/1-1:1.0").mkdir(parents=True)
    (pc.root / "sys/class/net/can0/device").unlink()
    pc.link("sys/class/net/can0/device",
            "../../../devices/pci0000:00/0000:00:14.0/usb1/1-1/1-1:1.0")
    pc.write("proc/irq/120/smp_affinity_list", "0\n")
    item = pc.item("can_irq")
    assert item.verdict == "ok"
    assert "via /sys/devices/pci0000:00/0000:00:14.0" in item.finding


def test_can_irq_without_cpu_and_on_vcan(pc):
    assert pc.item("can_irq", cpu=None).verdict == "info"
    pc.netdev("vcan0", flags="0xc1", operstate="unknown", txqueuelen=0)
    pc.ip["vcan0"] = [{"ifname": "vcan0", "linkinfo": {"info_kind": "vcan"}}]
    item = pc.item("can_irq", channel="vcan0")
    assert item.verdict == "info" and "virtual" in item.finding


# ------------------------------------------------------------------ THP, swap
@pytest.mark.parametrize("text, verdict", [("[always] madvise never", "warn"),
                                           ("always [madvise] never", "ok"),
                                           ("always madvise [never]", "ok")])
def test_thp(pc, text, verdict):
    pc.write("sys/kernel/mm/transparent_hugepage/enabled", text + "\n")
    item = pc.item("thp")
    assert item.verdict == verdict
    if verdict == "warn":
        assert "echo madvise > /sys/kernel/mm/transparent_hugepage/enabled" in item.fix


def test_thp_not_built_is_ok(pc):
    pc.remove("sys/kernel/mm/transparent_hugepage/enabled")
    assert pc.item("thp").verdict == "ok"


def test_swap(pc):
    assert pc.item("swap").verdict == "ok"
    pc.write("proc/swaps", "Filename\tType\tSize\tUsed\tPriority\n"
             "/dev/sda2 partition 4194300 1024 -2\n")
    item = pc.item("swap")
    assert item.verdict == "info" and "4 GiB on /dev/sda2" in item.finding
    assert "mlockall" in item.finding
    pc.caps(0)
    pc.limits(memlock="65536")
    item = pc.item("swap")
    assert_not_ok(item, "warn", "swapoff -a")


# ---------------------------------------------------------- memlock, SCHED_FIFO
def test_memlock(pc):
    item = pc.item("memlock")
    assert item.verdict == "ok" and "CAP_IPC_LOCK (root)" in item.finding
    pc.caps(0)
    pc.limits(memlock="unlimited")
    assert pc.item("memlock").verdict == "ok"
    pc.limits(memlock="8388608")
    item = pc.item("memlock")
    assert "8 MiB" in item.finding
    assert_not_ok(item, "warn", "memlock unlimited", "limits.d")
    pc.limits(memlock="8388608", memlock_hard="unlimited")
    assert "ulimit -l unlimited" in pc.item("memlock").fix


def test_sched_fifo_rights(pc):
    assert pc.item("sched_fifo").verdict == "ok"
    pc.caps(1 << 14)                       # CAP_IPC_LOCK only
    pc.limits(rtprio="99")
    item = pc.item("sched_fifo")
    assert item.verdict == "ok" and "99 >= 80" in item.finding
    pc.limits(rtprio="50")
    report = pc.run()
    item = report.item("sched_fifo")
    assert "50 < 80" in item.finding
    assert_not_ok(item, "fail", "root", "rtprio 99")
    assert report.exit_code == 1
    assert pc.item("sched_fifo", priority=50).verdict == "ok"
    assert pc.item("sched_fifo", priority=0).verdict == "info"
    pc.caps(1 << 23)                       # CAP_SYS_NICE without root
    assert pc.item("sched_fifo").verdict == "ok"


# ------------------------------------------------------------- CAN interface
def test_can_interface_up(pc):
    item = pc.item("can_interface")
    assert item.verdict == "ok"
    for word in ("can0: CAN", "up", "1000000 bit/s", "ERROR-ACTIVE", "txqueuelen 1000",
                 "no drops"):
        assert word in item.finding


def test_can_interface_down(pc):
    pc.netdev("can0", flags="0x80", operstate="down")
    pc.ip["can0"][0]["linkinfo"]["info_data"]["state"] = "STOPPED"
    report = pc.run()
    item = report.item("can_interface")
    assert "down" in item.finding
    assert_not_ok(item, "fail", "ip link set can0 up type can bitrate 1000000")
    assert report.exit_code == 1


def test_can_interface_bus_off(pc):
    data = pc.ip["can0"][0]["linkinfo"]["info_data"]
    data["state"] = "BUS-OFF"
    data["berr_counter"] = {"tx": 255, "rx": 0}
    item = pc.item("can_interface")
    assert "BUS-OFF" in item.finding and "tx 255" in item.finding
    assert_not_ok(item, "fail", "restart-ms", "termination")
    data["state"] = "ERROR-PASSIVE"
    assert pc.item("can_interface").verdict == "warn"


def test_can_interface_missing(pc):
    item = pc.item("can_interface", channel="can1")
    assert "no network interface can1" in item.finding and "can0" in item.finding
    assert_not_ok(item, "fail", "dmesg")
    assert pc.item("can_interface", channel="vcan7").fix.startswith("modprobe vcan")
    item = pc.item("can_interface", channel=None)          # vcan0 does not exist
    assert item.verdict == "info" and "embedded transport" in item.finding
    assert "--channel can0" in item.finding


def test_can_interface_default_vcan0(pc):
    pc.netdev("vcan0", flags="0xc1", operstate="unknown", txqueuelen=0)
    pc.ip["vcan0"] = [{"ifname": "vcan0", "linkinfo": {"info_kind": "vcan"}}]
    item = pc.item("can_interface", channel=None)
    assert item.verdict == "ok" and "vcan0: virtual vcan, up" in item.finding
    pc.netdev("vcan0", flags="0x80", operstate="down")
    assert_not_ok(pc.item("can_interface", channel=None), "fail", "ip link set vcan0 up")


def test_can_interface_queue_drops_and_bitrate(pc):
    pc.netdev("can0", txqueuelen=10, tx_dropped=17)
    pc.ip["can0"][0]["linkinfo"]["info_data"]["bittiming"]["bitrate"] = 500000
    item = pc.item("can_interface")
    assert "txqueuelen 10" in item.finding and "tx_dropped 17" in item.finding
    assert "500000" in item.finding
    assert_not_ok(item, "warn", "ip link set can0 txqueuelen 1000", "bitrate 1000000")


def test_can_interface_drops_alone(pc):
    pc.netdev("can0", rx_dropped=3, tx_dropped=2)
    item = pc.item("can_interface")
    assert "rx_dropped 3, tx_dropped 2" in item.finding
    assert_not_ok(item, "warn", "txqueuelen 2000", "ip -s link show can0")


def test_can_interface_not_can_and_without_ip(pc):
    pc.netdev("eth0", type_=1)
    item = pc.item("can_interface", channel="eth0")
    assert "not a CAN interface" in item.finding
    assert_not_ok(item, "fail", "--channel")
    del pc.ip["can0"]                                      # ip fails
    item = pc.item("can_interface")
    assert item.verdict == "ok" and "bitrate and bus state unknown" in item.finding


# ---------------------------------------------------------------------- floor
def test_floor_not_measured_with_no_floor(pc):
    item = pc.item("floor")
    assert item.verdict == "info" and pc.floor_calls == []


def test_floor_bad_figures_warn_with_the_ratio(pc):
    pc.floor[None].update(p99_9_us=480.0, max_us=2900.0, late_wakeups=5)
    pc.floor[0].update(p99_9_us=120.0, max_us=700.0, late_wakeups=1)
    stock_kernel(pc)
    pc.config(NONE_DYNAMIC_CONFIG)
    report = pc.run(floor=True, floor_s=1.0, cpu=None)
    item = report.item("floor")
    assert "4.0x" in item.finding and "p99.9 120 us" in item.finding and "480" in item.finding
    assert_not_ok(item, "warn", "kernel preemption", "CPU isolation")
    text = report.text()
    assert "without PM QoS" in text and "with PM QoS 0" in text


def test_floor_late_wakeup_or_refused_rights_warn(pc):
    pc.floor[0].update(late_wakeups=1)
    assert pc.item("floor", floor=True).verdict == "warn"
    pc.floor[0].update(late_wakeups=0, rt_policy_ok=False)
    item = pc.item("floor", floor=True)
    assert item.verdict == "warn" and "without SCHED_FIFO" in item.finding


def test_floor_names_a_pm_qos_request_held_by_another_process(pc):
    pc.write_bytes("dev/cpu_dma_latency", struct.pack("=i", 0))
    item = pc.item("floor", floor=True)
    assert item.verdict == "ok" and "another process held PM QoS at 0 us" in item.finding


def test_floor_error_is_an_unknown(pc):
    def broken(*a, **kw):
        raise FloorError("the real-time loop is not built (x); run scripts/setup")

    item = run_doctor(str(pc.root), cpu=3, channel="can0", ip_link=pc.ip_link,
                      measure=broken, floor_s=1.0).item("floor")
    assert item.finding.startswith("unknown: the floor loop did not run")
    assert_not_ok(item, "warn", "scripts/setup")


def test_one_short_real_floor_run(pc):
    report = run_doctor(str(pc.root), cpu=None, channel="can0", ip_link=pc.ip_link,
                        priority=0, floor_s=0.2)
    item = report.item("floor")
    assert item.verdict in ("ok", "warn")
    for run in ("without_pm_qos", "with_pm_qos"):
        fig = item.details[run]
        assert fig["samples"] > 0 and fig["p99_9_us"] is not None
    assert item.details["without_pm_qos"]["pm_qos"]["held"] is False


# ------------------------------------------------------------- odd files
@pytest.mark.parametrize("path, key", [
    ("proc/sys/kernel/sched_rt_runtime_us", "rt_throttling"),
    ("sys/devices/system/cpu/cpu3/cpufreq/scaling_governor", "governor"),
    ("sys/devices/system/cpu/cpu3/cpuidle/state2/latency", "idle_states"),
    ("sys/devices/system/cpu/cpu3/topology/thread_siblings_list", "smt"),
    ("proc/irq/45/smp_affinity_list", "can_irq"),
    ("sys/kernel/mm/transparent_hugepage/enabled", "thp"),
    ("proc/swaps", "swap"),
    ("sys/class/net/can0/flags", "can_interface"),
])
def test_garbage_makes_the_item_unknown(pc, path, key):
    pc.write_bytes(path, b"\x00\xff\xfe garbage \x01\n\n more")
    report = pc.run()
    item = report.item(key)
    assert item.verdict == "warn", item
    assert "unknown" in item.finding, item
    assert "the check failed" not in item.finding, item
    assert item.fix


@pytest.mark.parametrize("path", ["proc/self/status", "proc/self/limits", "proc/cmdline",
                                  "sys/devices/system/cpu/online", "proc/interrupts",
                                  "sys/devices/system/cpu/isolated", "sys/kernel/realtime",
                                  "proc/sys/kernel/version", "dev/cpu_dma_latency"])
def test_garbage_or_missing_files_never_crash(pc, path):
    pc.write_bytes(path, b"\x00\xff 1-x,, (\n")
    report = pc.run(cpu=None)
    assert all(i.verdict in doctor.VERDICTS and "the check failed" not in i.finding
               for i in report.items), report.text()
    pc.remove(path)
    report = pc.run(cpu=None)
    assert all("the check failed" not in i.finding for i in report.items), report.text()


def test_rights_unknown_without_status_and_limits(pc):
    pc.remove("proc/self/status")
    pc.remove("proc/self/limits")
    report = pc.run()
    for key in ("memlock", "sched_fifo"):
        assert report.item(key).finding.startswith("unknown:")


def test_an_empty_root_gives_a_report(tmp_path):
    report = run_doctor(str(tmp_path), floor=False)
    assert len(report.items) == 13
    assert all("the check failed" not in i.finding for i in report.items), report.text()


def test_cpulists():
    assert parse_cpulist("0-3,8,10-11\n") == {0, 1, 2, 3, 8, 10, 11}
    assert parse_cpulist("(null)") == set() and parse_cpulist("") == set()
    assert parse_cpulist("2-N", last_cpu=5) == {2, 3, 4, 5}
    assert parse_cpulist("0-7:2/4") == {0, 1, 4, 5}
    for bad in ("x", "3-1", "1,,2", "N", "0-7:2/0"):
        with pytest.raises(ValueError):
            parse_cpulist(bad)
    assert doctor.format_cpulist({0, 1, 2, 5, 7, 8}) == "0-2,5,7-8"


# ------------------------------------------------------------------- report
def test_report_text_and_json(pc):
    pc.write("sys/kernel/mm/transparent_hugepage/enabled", "[always] madvise never\n")
    pc.netdev("can0", flags="0x80", operstate="down")
    report = pc.run()
    text = report.text()
    lines = text.splitlines()
    verdict_lines = [ln for ln in lines if ln[:4] in ("FAIL", "WARN", "INFO", "OK  ")]
    order = [ln[:4].strip() for ln in verdict_lines]
    assert order == sorted(order, key=lambda v: ["FAIL", "WARN", "INFO", "OK"].index(v))
    assert order[0] == "FAIL" and "WARN" in order
    assert "fixes" in lines
    assert "echo madvise" in text and "ip link set can0 up" in text
    data = json.loads(report.json_text())
    assert data["exit_code"] == 1 and data["counts"]["fail"] == 1
    assert {i["key"] for i in data["items"]} == {i.key for i in report.items}
    assert data["items"][0]["verdict"] == "fail"


def test_bad_arguments():
    for kw, words in (({"priority": 120}, "priority"), ({"rate_hz": 5.0}, "rate"),
                      ({"floor_s": 0.0}, "floor"), ({"cpu": -1}, "cpu")):
        with pytest.raises(doctor.DoctorError, match=words):
            run_doctor("/", **kw)


# ---------------------------------------------------------------------- CLI
def run_cli(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_json_to_stdout_parses(capsys):
    code, out, err = run_cli(capsys, "doctor", "--no-floor", "--json", "-")
    data = json.loads(out)
    assert len(data["items"]) == 13
    assert code == data["exit_code"] == (1 if data["counts"]["fail"] else 0), err
    assert data["options"]["floor_s"] is None


def test_cli_table_and_json_file(capsys, tmp_path):
    path = tmp_path / "sub" / "doctor.json"
    code, out, err = run_cli(capsys, "doctor", "--no-floor", "--json", path)
    assert code in (0, 1), err
    assert "kernel preemption" in out and str(path) in out
    assert json.loads(path.read_text())["exit_code"] == code


def test_cli_passes_the_options(capsys, monkeypatch, pc):
    seen = {}

    def fake(**kw):
        seen.update(kw)
        return FakePC.run(pc, cpu=3, channel="nothere")

    monkeypatch.setattr(doctor, "run_doctor", fake)
    code, out, err = run_cli(capsys, "doctor", "--cpu", 3, "--channel", "nothere", "--priority",
                             70, "--rate", 1000, "--floor-s", 2.5)
    assert code == 1                                     # the missing --channel fails
    assert "no network interface nothere" in out
    assert {k: seen[k] for k in ("cpu", "channel", "priority", "rate_hz", "floor_s", "floor")} == {
        "cpu": 3, "channel": "nothere", "priority": 70, "rate_hz": 1000.0, "floor_s": 2.5,
        "floor": True}


@pytest.mark.parametrize("argv, words", [
    (["--priority", "120"], "--priority"),
    (["--floor-s", "0"], "--floor-s"),
    (["--rate", "fast"], "--rate"),
    (["--cpu", "-1"], "--cpu"),
    (["--cpu", "4096", "--no-floor"], "not online"),
    (["--bogus"], "--bogus"),
])
def test_cli_bad_options_one_line_exit_2(capsys, argv, words):
    code, out, err = run_cli(capsys, "doctor", *argv)
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("dct-hil: error: ") and words in lines[0], err
