//! The memory guard's reading of the available memory: the machine's `MemAvailable` and the
//! cgroup v2 / v1 limits, on fake file-system trees (`available_memory_under`).

use std::fs;

use freefall::io::{available_memory_under, MemoryLimit};

const GIB: u64 = 1 << 30;

/// A fake file-system root: `files` are (path under root, content).
fn tree(files: &[(&str, String)]) -> tempfile::TempDir {
    let root = tempfile::tempdir().unwrap();
    for (path, content) in files {
        let p = root.path().join(path);
        fs::create_dir_all(p.parent().unwrap()).unwrap();
        fs::write(p, content).unwrap();
    }
    root
}

/// `MemAvailable` of `bytes` (a whole number of kB).
fn meminfo(bytes: u64) -> (&'static str, String) {
    (
        "proc/meminfo",
        format!(
            "MemTotal:       32000000 kB\nMemFree:         1000000 kB\nMemAvailable:   {} kB\n",
            bytes / 1024
        ),
    )
}

fn file(path: &'static str, content: impl ToString) -> (&'static str, String) {
    (path, content.to_string())
}

// Oracle for every case: the minimum computed by hand from the fake files.

#[test]
fn cgroup_v2_limit_below_the_machine_applies() {
    let root = tree(&[
        meminfo(8 * GIB),
        file("proc/self/cgroup", "0::/job/step\n"),
        file("sys/fs/cgroup/job/memory.max", 2 * GIB),
        file("sys/fs/cgroup/job/memory.current", 3 * GIB / 2),
        file(
            "sys/fs/cgroup/job/memory.stat",
            format!("anon 1000\nfile 5000\ninactive_file {}\n", GIB / 4),
        ),
        file("sys/fs/cgroup/job/step/memory.max", "max\n"),
        file("sys/fs/cgroup/job/step/memory.current", GIB),
    ]);
    let a = available_memory_under(root.path()).unwrap();
    // 2 GiB - (1.5 GiB - 0.25 GiB) = 0.75 GiB < 8 GiB.
    assert_eq!(a.bytes, 3 * GIB / 4);
    assert_eq!(
        a.limit,
        MemoryLimit::Cgroup {
            version: 2,
            dir: root.path().join("sys/fs/cgroup/job")
        }
    );
    let text = a.limit.to_string();
    assert!(text.contains("memory.max - memory.current") && text.contains("job"));
}

#[test]
fn cgroup_v2_max_is_no_limit() {
    let root = tree(&[
        meminfo(8 * GIB),
        file("proc/self/cgroup", "0::/user.slice\n"),
        file("sys/fs/cgroup/user.slice/memory.max", "max\n"),
        file("sys/fs/cgroup/user.slice/memory.current", 5 * GIB),
    ]);
    let a = available_memory_under(root.path()).unwrap();
    assert_eq!((a.bytes, a.limit), (8 * GIB, MemoryLimit::Machine));
}

#[test]
fn cgroup_limit_above_the_machine_leaves_the_machine() {
    let root = tree(&[
        meminfo(8 * GIB),
        file("proc/self/cgroup", "0::/big\n"),
        file("sys/fs/cgroup/big/memory.max", 64 * GIB),
        file("sys/fs/cgroup/big/memory.current", GIB),
    ]);
    let a = available_memory_under(root.path()).unwrap();
    // min(8 GiB, 64 - 1 GiB) = 8 GiB.
    assert_eq!((a.bytes, a.limit), (8 * GIB, MemoryLimit::Machine));
}

#[test]
fn cgroup_v1_limit_applies_and_its_unlimited_ancestor_does_not() {
    let root = tree(&[
        meminfo(16 * GIB),
        file(
            "proc/self/cgroup",
            "5:cpu,cpuacct:/slurm/job_5\n4:memory:/slurm/job_5\n0::/\n",
        ),
        file(
            "sys/fs/cgroup/memory/memory.limit_in_bytes",
            9223372036854771712u64,
        ),
        file("sys/fs/cgroup/memory/memory.usage_in_bytes", 10 * GIB),
        file(
            "sys/fs/cgroup/memory/slurm/job_5/memory.limit_in_bytes",
            4 * GIB,
        ),
        file(
            "sys/fs/cgroup/memory/slurm/job_5/memory.usage_in_bytes",
            3 * GIB,
        ),
        file(
            "sys/fs/cgroup/memory/slurm/job_5/memory.stat",
            format!(
                "cache 1\ninactive_file 7\ntotal_inactive_file {}\n",
                GIB / 2
            ),
        ),
    ]);
    let a = available_memory_under(root.path()).unwrap();
    // 4 GiB - (3 GiB - 0.5 GiB) = 1.5 GiB < 16 GiB; the root's limit is "none".
    assert_eq!(a.bytes, 3 * GIB / 2);
    assert_eq!(
        a.limit,
        MemoryLimit::Cgroup {
            version: 1,
            dir: root.path().join("sys/fs/cgroup/memory/slurm/job_5")
        }
    );
    assert!(a.limit.to_string().contains("memory.limit_in_bytes"));
}

#[test]
fn a_container_sees_its_limit_at_the_hierarchy_root() {
    // The host's path of the cgroup does not exist inside the container's mount: the
    // limit is read where the container sees its cgroup, at the root.
    let root = tree(&[
        meminfo(30 * GIB),
        file("proc/self/cgroup", "0::/docker/0123abc\n"),
        file("sys/fs/cgroup/memory.max", 6 * GIB),
        file("sys/fs/cgroup/memory.current", 2 * GIB),
    ]);
    let a = available_memory_under(root.path()).unwrap();
    assert_eq!(a.bytes, 4 * GIB);
}

#[test]
fn a_hybrid_system_reads_v2_under_unified() {
    let root = tree(&[
        meminfo(30 * GIB),
        file("proc/self/cgroup", "4:memory:/\n0::/job\n"),
        file("sys/fs/cgroup/unified/cgroup.controllers", ""),
        file("sys/fs/cgroup/unified/job/memory.max", 3 * GIB),
        file("sys/fs/cgroup/unified/job/memory.current", GIB),
    ]);
    let a = available_memory_under(root.path()).unwrap();
    assert_eq!(a.bytes, 2 * GIB);
}

#[test]
fn without_cgroups_the_machine_applies_and_without_meminfo_nothing() {
    let root = tree(&[meminfo(8 * GIB)]);
    let a = available_memory_under(root.path()).unwrap();
    assert_eq!((a.bytes, a.limit), (8 * GIB, MemoryLimit::Machine));
    let empty = tree(&[]);
    assert_eq!(available_memory_under(empty.path()), None);
    // A cgroup limit without meminfo is still a limit.
    let only = tree(&[
        file("proc/self/cgroup", "0::/\n"),
        file("sys/fs/cgroup/memory.max", GIB),
        file("sys/fs/cgroup/memory.current", 0),
    ]);
    assert_eq!(available_memory_under(only.path()).unwrap().bytes, GIB);
}
