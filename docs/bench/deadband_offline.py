# Perceptual deadband offline: python3 docs/bench/deadband_offline.py BRIDGE_RECORDING.csv [0.07]
# Applies the force-stream rule (7 %, 1 mN floor, 5 ms heartbeat, contact flag) to a bridge
# --record file and prints the messages saved and the force error of a zero-order hold.
import csv, sys, math
rows=list(csv.DictReader(open(sys.argv[1])))
k=float(sys.argv[2]) if len(sys.argv)>2 else 0.07
t=[float(r['t_s']) for r in rows]
f=[[float(r[c]) for c in ('fx_n','fy_n','fz_n')] for r in rows]
c=[r['in_contact']=='true' for r in rows]
norm=lambda v: math.sqrt(sum(x*x for x in v))
held=None; last_t=None; last_c=None; sent=0; se=0; mx=0; peak=max(norm(v) for v in f)
for i in range(len(rows)):
    send = held is None or (t[i]-last_t)>=0.005 or c[i]!=last_c
    if not send:
        d=norm([a-b for a,b in zip(f[i],held)])
        send = d>k*norm(held) and d>1e-3
    if send: held=f[i]; last_t=t[i]; last_c=c[i]; sent+=1
    e=norm([a-b for a,b in zip(f[i],held)]); se+=e*e; mx=max(mx,e)
n=len(rows)
print("k=%.2f: %d of %d force messages sent (%.1f %% fewer); error vs every message: rms %.2e N (%.2f %% of the %.4f N peak), max %.2e N (%.1f %%)"%(k,sent,n,100*(1-sent/n),math.sqrt(se/n),100*math.sqrt(se/n)/peak,peak,mx,100*mx/peak))
