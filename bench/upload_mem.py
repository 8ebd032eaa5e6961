# The coordinator's memory under concurrent file uploads: starts `furnace serve` (BINARY), PUTs
# N bodies of SIZE MiB at once (wrong hashes: each body is read whole, then refused), prints
# the peak resident memory (VmHWM).   python3 bench/upload_mem.py BINARY N SIZE
import sys, subprocess, threading, time, http.client, shutil
binary, n, size = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]) << 20
data = '/tmp/upmem-data'
shutil.rmtree(data, ignore_errors=True)
p = subprocess.Popen([binary, 'serve', '--data-dir', data, '--bind', '127.0.0.1:0'], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
host, port = p.stdout.readline().decode().strip().split('http://')[1].split(':')
body = bytes(range(256)) * (size // 256)
codes = []
def up(k):
    c = http.client.HTTPConnection(host, int(port), timeout=300)
    c.request('PUT', '/v1/files/' + ('%064x' % (k + 1)), body=body)
    codes.append(c.getresponse().status)
t = time.time()
th = [threading.Thread(target=up, args=(k,)) for k in range(n)]
[x.start() for x in th]; [x.join() for x in th]
hwm = [l for l in open(f'/proc/{p.pid}/status') if l.startswith('VmHWM')][0].split()[1]
print(f'{binary}: {n} x {size>>20} MiB uploads, codes {sorted(set(codes))}, {time.time()-t:.1f} s, peak RSS {int(hwm)/1024:.0f} MiB')
p.kill()
shutil.rmtree(data, ignore_errors=True)
