# The coordinator's memory when a large job is cancelled: starts `furnace serve` (BINARY),
# submits examples/cbox.xml with a WIDTH x HEIGHT film at 1 spp (nothing is rendered: no
# worker), cancels it, and prints the peak resident memory (VmHWM) after the submission and
# after the cancel, which stores the image so far (checkpoint and result.exr).
#   python3 bench/cancel_mem.py BINARY [WIDTH HEIGHT]
import sys, subprocess, time, json, shutil, os, http.client, re
binary = sys.argv[1]
width, height = (int(sys.argv[2]), int(sys.argv[3])) if len(sys.argv) > 3 else (8192, 4096)
data, scene_dir = '/tmp/cancelmem-data', '/tmp/cancelmem-scene'
for d in (data, scene_dir):
    shutil.rmtree(d, ignore_errors=True)
shutil.copytree(os.path.join(os.path.dirname(__file__), '..', 'examples'), scene_dir)
scene = os.path.join(scene_dir, 'cbox.xml')
xml = open(scene).read()
xml = re.sub(r'name="width" value="\d+"', f'name="width" value="{width}"', xml)
xml = re.sub(r'name="height" value="\d+"', f'name="height" value="{height}"', xml)
open(scene, 'w').write(xml)
p = subprocess.Popen([binary, 'serve', '--data-dir', data, '--bind', '127.0.0.1:0'],
                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
url = p.stdout.readline().decode().strip().split(' ')[-1]
host, port = url.split('http://')[1].split(':')
hwm = lambda: int([l for l in open(f'/proc/{p.pid}/status') if l.startswith('VmHWM')][0].split()[1]) >> 10
out = subprocess.run([binary, 'submit', '--coordinator', url, '--spp', '1', scene],
                     capture_output=True, text=True, check=True).stdout
job = re.search(r'[0-9a-f]{16}', out).group(0)
def call(method, path):
    c = http.client.HTTPConnection(host, int(port), timeout=600)
    c.request(method, path)
    r = c.getresponse()
    return r.status, r.read()
submitted = hwm()
t = time.time()
status, _ = call('POST', f'/v1/jobs/{job}/cancel')
took = time.time() - t
st = json.loads(call('GET', f'/v1/jobs/{job}')[1])
size = os.path.getsize(f'{data}/jobs/{job}/result.exr')
print(f'{binary}: {width} x {height}, peak RSS {submitted} MiB after submit, {hwm()} MiB after cancel '
      f'(answered {status} in {took:.1f} s, state {st["state"]}, result.exr {size >> 20} MiB)')
p.kill()
for d in (data, scene_dir):
    shutil.rmtree(d, ignore_errors=True)
