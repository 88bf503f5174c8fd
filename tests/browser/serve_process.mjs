// `dojo serve` as a child process for the browser scripts: started on a free port, waited for until
// its models are loaded (/health answers 200). On failure the process is killed and the error
// carries its log.
import { spawn } from "node:child_process";

// Resolves to { server (the child process), base ("http://127.0.0.1:PORT"), log() (its output so far) }.
export async function startServer(exe, args, { startSeconds = 60, loadSeconds = 60 } = {}) {
  const server = spawn(exe, args, { stdio: ["ignore", "pipe", "pipe"] });
  let log = "";
  try {
    const port = await new Promise((resolve, reject) => {
      const timer = setTimeout(() => reject(new Error("server did not start:\n" + log)), startSeconds * 1000);
      const onData = (d) => {
        log += d;
        const m = /listening on https?:\/\/[\d.]+:(\d+)/.exec(log);
        if (m) { clearTimeout(timer); resolve(Number(m[1])); }
      };
      server.stderr.on("data", onData);
      server.stdout.on("data", onData);
      server.on("exit", (code) => reject(new Error(`server exited (${code}):\n${log}`)));
    });
    const base = `http://127.0.0.1:${port}`;
    for (let i = 0; ; ++i) {
      const r = await fetch(base + "/health").catch(() => null);
      if (r && r.status === 200) break;
      if (i > loadSeconds * 10) throw new Error(`the models did not load within ${loadSeconds} s:\n` + log);
      await new Promise((r) => setTimeout(r, 100));
    }
    return { server, base, log: () => log };
  } catch (e) {
    server.kill("SIGKILL");
    throw e;
  }
}
