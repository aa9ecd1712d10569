// The field directions on a rotatable 3-D sphere (canvas 2-D, no library): orthographic view,
// the equal-area cells shaded seen / not yet, the stored samples as dots, the body axes, the
// largest gap's edge, the ring and the newest field direction. Drag to turn, double-click to
// reset. Inlined into live.html by http_page (nothing loaded from elsewhere).
"use strict";
// (x, y, z) unit vector → cell index of the equal-area partition (bands north first)
function cellIndex(cells){
  const ze=cells.z_edges,cn=cells.counts,off=[0];
  for(let i=0;i<cn.length;i++)off.push(off[i]+cn[i]);
  return (x,y,z)=>{let b=0;while(b<cn.length-1&&z<ze[b+1])b++;
    const n=cn[b];return off[b]+Math.min(Math.floor((Math.atan2(y,x)+Math.PI)*n/(2*Math.PI)),n-1);};
}
const M3={
  mul:(a,b)=>a.map(r=>[0,1,2].map(j=>r[0]*b[0][j]+r[1]*b[1][j]+r[2]*b[2][j])),
  rotX:a=>[[1,0,0],[0,Math.cos(a),-Math.sin(a)],[0,Math.sin(a),Math.cos(a)]],
  rotY:a=>[[Math.cos(a),0,Math.sin(a)],[0,1,0],[-Math.sin(a),0,Math.cos(a)]],
  apply:(m,v)=>m.map(r=>r[0]*v[0]+r[1]*v[1]+r[2]*v[2]),
};
// body → view (view: x right, y up, z towards the viewer); body +X towards the viewer, +Y
// right, +Z up, then turned so the nose, the left side and the top are all in sight
const VIEW0=M3.mul(M3.rotX(0.45),M3.mul(M3.rotY(-0.7),[[0,1,0],[0,0,1],[1,0,0]]));
const SEEN=[34,170,119],UNSEEN=[214,214,214];
const AXES=[["+X",[1,0,0],"#c22"],["−X",[-1,0,0],"#c22"],["+Y",[0,1,0],"#282"],
            ["−Y",[0,-1,0],"#282"],["+Z",[0,0,1],"#22c"],["−Z",[0,0,-1],"#22c"]];

function Sphere3D(canvas){
  const g=canvas.getContext("2d"),W=canvas.width,H=canvas.height,cx=W/2,cy=H/2,R=Math.min(W,H)/2-34;
  let view=VIEW0,last=null,drag=null,pending=false;
  const project=d=>{const v=M3.apply(view,d);return [cx+v[0]*R,cy-v[1]*R,v[2]];};
  function circle(center,angle,style,dash){   // directions at `angle` (rad) from `center`; front half
    const c=center,a=Math.abs(c[0])<0.9?[1,0,0]:[0,1,0],dot=a[0]*c[0]+a[1]*c[1]+a[2]*c[2];
    let e1=a.map((v,i)=>v-dot*c[i]);const n=Math.hypot(...e1);e1=e1.map(v=>v/n);
    const e2=[c[1]*e1[2]-c[2]*e1[1],c[2]*e1[0]-c[0]*e1[2],c[0]*e1[1]-c[1]*e1[0]];
    const ca=Math.cos(angle),sa=Math.sin(angle);
    g.strokeStyle=style;g.lineWidth=2;g.setLineDash(dash||[]);g.beginPath();let pen=false;
    for(let k=0;k<=120;k++){const p=2*Math.PI*k/120,cp=Math.cos(p),sp=Math.sin(p);
      const [x,y,z]=project([0,1,2].map(i=>ca*c[i]+sa*(cp*e1[i]+sp*e2[i])));
      if(z<0){pen=false;continue}pen?g.lineTo(x,y):g.moveTo(x,y);pen=true;}
    g.stroke();g.setLineDash([]);
  }
  function draw(s){
    if(s)last=s;s=last;if(!s)return;
    g.clearRect(0,0,W,H);
    const img=g.getImageData(0,0,W,H),px=img.data,occ=s.occupied,cell=cellIndex(s.cells),m=view;
    for(let y=Math.floor(cy-R);y<=Math.ceil(cy+R);y++)for(let x=Math.floor(cx-R);x<=Math.ceil(cx+R);x++){
      const u=(x-cx)/R,v=(cy-y)/R,r2=u*u+v*v;if(r2>1)continue;const w=Math.sqrt(1-r2);
      const bx=m[0][0]*u+m[1][0]*v+m[2][0]*w,by=m[0][1]*u+m[1][1]*v+m[2][1]*w,bz=m[0][2]*u+m[1][2]*v+m[2][2]*w;
      const col=occ[cell(bx,by,bz)]==="1"?SEEN:UNSEEN;
      const shade=(Math.abs(bz)<0.012?0.7:1)*(0.55+0.45*w),i=(y*W+x)*4;
      px[i]=col[0]*shade;px[i+1]=col[1]*shade;px[i+2]=col[2]*shade;px[i+3]=255;
    }
    g.putImageData(img,0,0);
    g.strokeStyle="#888";g.lineWidth=1;g.beginPath();g.arc(cx,cy,R,0,2*Math.PI);g.stroke();
    g.fillStyle="#0a4a33";
    (s.directions||[]).forEach(d=>{const [x,y,z]=project(d);if(z>=0)g.fillRect(x-1.5,y-1.5,3,3);});
    if(s.gap&&s.gap.deg>=20){circle(s.gap.center,s.gap.deg*Math.PI/180,"#c00");
      const [x,y,z]=project(s.gap.center);
      if(z>=0){g.strokeStyle="#c00";g.lineWidth=2;g.beginPath();g.arc(x,y,6,0,2*Math.PI);g.stroke();}}
    const r=s.ring;
    if(r){circle(r.down,Math.PI/2-r.dip_deg*Math.PI/180,"#a0a",[5,3]);
      if(r.field){const [x,y,z]=project(r.field);
        if(z>=0){g.fillStyle="#06c";g.beginPath();g.arc(x,y,5,0,2*Math.PI);g.fill();}}}
    g.font="12px sans-serif";g.textAlign="center";g.textBaseline="middle";
    AXES.forEach(([name,d,col])=>{const v=M3.apply(view,d),front=v[2]>=0;
      const at=k=>[cx+v[0]*R*k,cy-v[1]*R*k];
      if(front){const [x0,y0]=at(1),[x1,y1]=at(1.12);g.strokeStyle=col;g.lineWidth=2;
        g.beginPath();g.moveTo(x0,y0);g.lineTo(x1,y1);g.stroke();}
      const [x,y]=at(front?1.22:1.0);g.strokeStyle="rgba(255,255,255,.85)";g.lineWidth=3;
      g.strokeText(name,x,y);g.fillStyle=front?col:"#777";g.fillText(name,x,y);});
    g.textAlign="start";g.textBaseline="alphabetic";
  }
  const redraw=()=>{if(pending)return;pending=true;requestAnimationFrame(()=>{pending=false;draw();});};
  const scale=()=>canvas.width/(canvas.clientWidth||canvas.width);
  canvas.style.touchAction="none";canvas.style.cursor="grab";
  canvas.addEventListener("pointerdown",e=>{drag=[e.clientX,e.clientY];canvas.setPointerCapture(e.pointerId);});
  canvas.addEventListener("pointermove",e=>{if(!drag)return;const k=scale()/R;
    const dx=(e.clientX-drag[0])*k,dy=(e.clientY-drag[1])*k;drag=[e.clientX,e.clientY];
    view=M3.mul(M3.mul(M3.rotY(dx),M3.rotX(dy)),view);redraw();});
  const stop=()=>{drag=null;};
  canvas.addEventListener("pointerup",stop);canvas.addEventListener("pointercancel",stop);
  canvas.addEventListener("dblclick",()=>{view=VIEW0;redraw();});
  return {draw,get view(){return view;}};
}
